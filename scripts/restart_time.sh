#!/usr/bin/env bash
# How long `evermap-server serve` takes to come back on a store: from start to "gRPC serving", i.e. the
# replay of every site's log (docs/BENCHMARK-HISTORY.md, "Restart time grows with a site's log").
#
#   scripts/restart_time.sh out/soak60m/data         # a store an `evermap-demo load` run left
#
# Works on a copy (the original is never opened): lists the copy's sites with `evermap-server site list`,
# serves all of them (robots and tokens made up: nobody connects), prints the seconds until gRPC serves
# and each site's replay line (a site whose checkpoint covers its log starts unloaded and replays
# nothing: scripts/unload_time.sh measures its restore), then stops the server with SIGTERM. Environment: BIN (default
# target/release/evermap-server; build it with `cargo build --release --workspace`), OUT (default
# out/restart_time), IN_PLACE (1: serve the store itself, not a copy; serving writes to it).
set -euo pipefail

STORE=${1:?usage: scripts/restart_time.sh STORE_DIR}
BIN=${BIN:-target/release/evermap-server}
OUT=${OUT:-out/restart_time}
# shellcheck source=serve_store.sh
source "$(dirname "$0")/serve_store.sh"
store_prepare "$STORE" "$OUT"
{ cat "$OUT/list.toml"; store_site_entries restart-robot; } >"$OUT/serve.toml"

start=$(date +%s.%N)
store_serve "$OUT/serve.toml" "$OUT/serve.log"
store_wait_for "gRPC serving"
end=$(date +%s.%N)
echo "$n site(s) serving after $(echo "$end - $start" | bc) s"
sed 's/\x1b\[[0-9;]*m//g' "$OUT/serve.log" | grep "site log replayed" | sed 's/.*site=/  site=/'
store_stop
