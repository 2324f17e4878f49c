#!/usr/bin/env bash
# How long `evermap-server serve` takes to come back on a store: from start to "gRPC serving", i.e. the
# replay of every site's log (BENCHMARKS.md, "Restart time grows with a site's log").
#
#   scripts/restart_time.sh out/soak60m/data         # a store an `evermap-demo load` run left
#
# Works on a copy (the original is never opened): lists the copy's sites with `evermap-server site list`,
# serves all of them (robots and tokens made up: nobody connects), prints the seconds until gRPC serves
# and each site's replay line, then stops the server with SIGTERM. Environment: BIN (default
# target/release/evermap-server; build it with `cargo build --release --workspace`), OUT (default
# out/restart_time).
set -euo pipefail

STORE=${1:?usage: scripts/restart_time.sh STORE_DIR}
BIN=${BIN:-target/release/evermap-server}
OUT=${OUT:-out/restart_time}
[ -x "$BIN" ] || { echo "$BIN is missing: cargo build --release --workspace" >&2; exit 1; }
[ -d "$STORE" ] || { echo "no store at $STORE" >&2; exit 1; }

rm -rf "$OUT" && mkdir -p "$OUT"
cp -r "$STORE" "$OUT/data"
DATA=$(cd "$OUT/data" && pwd)
printf 'listen = "127.0.0.1:0"\nmetrics_listen = "127.0.0.1:0"\n[storage]\npath = "%s"\n' "$DATA" >"$OUT/list.toml"
SITES=$("$BIN" site list --config "$OUT/list.toml" | cut -f1)
[ -n "$SITES" ] || { echo "the store at $STORE holds no site" >&2; exit 1; }
cp "$OUT/list.toml" "$OUT/serve.toml"
n=0
for site in $SITES; do
  n=$((n + 1))
  printf '\n[[sites]]\nid = "%s"\nrobots = [{ id = "restart-robot", token = "restart-token-%d" }]\n' "$site" "$n" >>"$OUT/serve.toml"
done

start=$(date +%s.%N)
NO_COLOR=1 "$BIN" serve --config "$OUT/serve.toml" >"$OUT/serve.log" 2>&1 &
pid=$!
trap 'kill -TERM $pid 2>/dev/null || true' EXIT
# Bounded: an hour at most.
for _ in $(seq 1 18000); do
  grep -q "gRPC serving" "$OUT/serve.log" && break
  kill -0 "$pid" 2>/dev/null || { echo "the server exited:" >&2; tail -20 "$OUT/serve.log" >&2; exit 1; }
  sleep 0.2
done
grep -q "gRPC serving" "$OUT/serve.log" || { echo "not serving after an hour" >&2; exit 1; }
end=$(date +%s.%N)
echo "$n site(s) serving after $(echo "$end - $start" | bc) s"
sed 's/\x1b\[[0-9;]*m//g' "$OUT/serve.log" | grep "site log replayed" | sed 's/.*site=/  site=/'
kill -TERM "$pid"
wait "$pid"
trap - EXIT
