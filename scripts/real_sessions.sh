#!/usr/bin/env bash
# The nine real-recording session runs: MIT CSAIL, ACES and Intel each cut into 2, 3 and 5 sessions and
# lived as a robot would (`evermap-agent sessions`, scored by the recording's relations), then one table of
# them (scripts/real_sessions_table.py): when each later session was placed and committed, wrong placements,
# the cross-session relations smoothed and at the time.
#
#   scripts/real_sessions.sh [OUT_DIR]          (default out/sessions; each run in OUT_DIR/R-N)
#
# Environment: AGENT (default target/release/evermap-agent), CONFIG (a TOML file passed as --config; the
# figures in BENCHMARKS.md are scored without one), RECORDINGS (default "mit-csail aces intel"), SPLITS
# (default "2 3 5"), JOBS (parallel runs, default 2). A run whose report.json exists is not run again, so an
# interrupted set resumes where it stopped; delete OUT_DIR to start over (do so after changing the engine).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-out/sessions}
agent=${AGENT:-target/release/evermap-agent}
recordings=${RECORDINGS:-"mit-csail aces intel"}
splits=${SPLITS:-"2 3 5"}
jobs=${JOBS:-2}
datasets=../shared/datasets
if [[ ! -x $agent ]]; then
  echo "no $agent: build it first (cargo build --release --workspace)" >&2
  exit 1
fi
mkdir -p "$out"
run_one() {
  local r=$1 n=$2 dir=$out/$1-$2
  mkdir -p "$dir"
  if "$agent" sessions --input "$datasets/rosbag1/$r.orig.bag" --split "$n" \
      --relations "$datasets/relations/$r.relations" ${config:+--config "$config"} \
      --out "$dir.partial" >"$dir/stdout" 2>"$dir/stderr"; then
    mv "$dir.partial"/* "$dir"/ && rmdir "$dir.partial"
    echo "done $r ÷ $n" >&2
  else
    echo "FAILED $r ÷ $n (see $dir/stderr)" >&2
  fi
}
export -f run_one
config=${CONFIG:-}
export out agent datasets config
for r in $recordings; do
  for n in $splits; do
    [[ -f $out/$r-$n/report.json ]] || echo "$r $n"
  done
done | xargs -r -P "$jobs" -L 1 bash -c 'run_one $0 $1'
python3 scripts/real_sessions_table.py "$out"
