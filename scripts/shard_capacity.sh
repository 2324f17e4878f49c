#!/usr/bin/env bash
# How many sites one server instance holds, and how many robots per site, at the fleet load benchmark's
# latency goal (submap finished on a robot -> its version in every cache of the site, p50 < 2 s), and
# the memory per site (issue 16 §4). Runs `evermap-demo load` once per point and prints one line per run.
#
#   scripts/shard_capacity.sh                      # the default points
#   POINTS="10x2 20x2" DURATION=60 scripts/shard_capacity.sh
#
# A point is SITESxROBOTS_PER_SITE. Environment: BIN (default target/release/evermap-demo; build it
# with `cargo build --release --workspace`), DURATION (seconds of cleaning streamed per robot, default
# 60), SPREAD (seconds over which the robots start, `load --start-spread-s`, default 2: every session
# ends in the same 2 s), OUT (default out/shard_capacity; each run writes OUT/POINT/report.json and OUT/POINT.log).
# Memory per site: the difference of peak RSS between two points with the same robots per site, divided
# by the difference in sites (it includes those robots' prepared sessions and caches, which live in the
# same process: an upper bound for the server's share).
set -euo pipefail

BIN=${BIN:-target/release/evermap-demo}
DURATION=${DURATION:-60}
SPREAD=${SPREAD:-2}
OUT=${OUT:-out/shard_capacity}
POINTS=${POINTS:-"10x2 20x2 5x5"}

if [[ ! -x "$BIN" ]]; then
    echo "no $BIN: build it with 'cargo build --release --workspace' or set BIN" >&2
    exit 1
fi
mkdir -p "$OUT"
printf '%-8s %6s %6s %9s %9s %9s %7s %9s %9s\n' point sites robots p50_s p95_s undeliv cores peak_mb wall_s
for point in $POINTS; do
    sites=${point%x*}
    per_site=${point#*x}
    agents=$((sites * per_site))
    "$BIN" load --sites "$sites" --agents "$agents" --duration-s "$DURATION" --start-spread-s "$SPREAD" --out "$OUT/$point" \
        >"$OUT/$point.log" 2>&1
    python3 - "$OUT/$point/report.json" "$point" "$sites" "$agents" <<'PY'
import json, sys
report = json.load(open(sys.argv[1]))
latency = report["submap_latency_s"]["to_every_robot_of_the_site"]
server = report["server_process"]
print(f'{sys.argv[2]:<8} {sys.argv[3]:>6} {sys.argv[4]:>6} {latency["p50"]:>9.2f} {latency["p95"]:>9.2f} '
      f'{report["submap_latency_s"]["undelivered"]:>9} {server["cores_busy"]:>7.2f} '
      f'{server["peak_rss_mb"]:>9.0f} {report["wall_time_s"]:>9.0f}')
PY
done
