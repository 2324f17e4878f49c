#!/usr/bin/env bash
# The live ROS 2 benchmark (issue 15 §2): a shared recording replayed live over zenoh under rmw_zenoh's keys
# by the independent Python robot at SPEED × real time, mapped by `evermap-agent offline --ros2`, then the
# same recording mapped from the file; prints both runs' relations error and the live counts.
#
#   cargo build --release --workspace
#   bash scripts/ros2_live_benchmark.sh [RECORDING=mit-csail] [SPEED=5] [OUT=out/live-RECORDING]
set -euo pipefail
cd "$(dirname "$0")/.."
rec="${1:-mit-csail}"
speed="${2:-5}"
out="${3:-out/live-$rec}"
port="${EVERMAP_BENCH_PORT:-17447}"
py="$(bash scripts/ros2_venv.sh)"
bin="${EVERMAP_BIN:-target/release}"  # the directory of evermap-agent
relations="../shared/datasets/relations/$rec.relations"
mkdir -p "$out/live" "$out/file"
"$bin"/evermap-agent offline --ros2 --zenoh-listen "tcp/127.0.0.1:$port" --until-idle-s 5 \
  --relations "$relations" --out "$out/live" &
agent=$!
"$py" scripts/ros2_live_robot.py --bag "../shared/datasets/rosbag2-derived/$rec" \
  --connect "tcp/127.0.0.1:$port" --speed "$speed" --wait-s 30 --linger-s 120 --quiet-s 8 \
  --summary "$out/robot.json"
wait "$agent"
"$bin"/evermap-agent offline --input "../shared/datasets/rosbag2-derived/$rec" \
  --relations "$relations" --out "$out/file" > /dev/null
"$py" - "$out" <<'PY'
import json, sys
out = sys.argv[1]
live = json.load(open(f"{out}/live/report.json"))
file = json.load(open(f"{out}/file/report.json"))
robot = json.load(open(f"{out}/robot.json"))
print(json.dumps({
    "sent": robot["sent"], "replay_s": robot["replay_s"],
    "received": live["live"]["received"], "decoded": live["live"]["decoded"],
    "dropped": live["live"]["dropped"], "repeated_stamp": live["live"]["stats"]["repeated_stamp"],
    "scans_live": live["scans"], "scans_file": file["scans"],
    "trans_abs_mean_m_live": live["relations"]["trans_abs_mean_m"],
    "trans_abs_mean_m_file": file["relations"]["trans_abs_mean_m"],
    "relations_live": live["relations"], "relations_file": file["relations"],
    "wall_live_s": live["wall_time_s"], "maps_received": robot["maps_received"],
    "poses_received": robot["poses_received"], "published": live["live"]["published"],
}, indent=1))
PY
