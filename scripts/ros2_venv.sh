#!/usr/bin/env bash
# Creates (only when missing) the Python environment of the live ROS 2 test and benchmark:
# target/ros2-venv with pinned `rosbags` (reads recordings, CDR, RIHS01 type hashes) and `eclipse-zenoh`
# (the same zenoh release as the Rust crate). `.ci/run` calls it; so can you. Prints the interpreter path.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${EVERMAP_ROS2_VENV:-target/ros2-venv}"
marker="$venv/.evermap-ros2-deps-1"
if [ ! -f "$marker" ]; then
  rm -rf "$venv"
  python3 -m venv "$venv"
  "$venv/bin/pip" install --quiet --disable-pip-version-check \
    "rosbags==0.11.9" "eclipse-zenoh==1.10.2" "numpy==2.4.6"
  touch "$marker"
fi
echo "$venv/bin/python"
