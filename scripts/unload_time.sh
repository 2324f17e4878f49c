#!/usr/bin/env bash
# How long a request to an unloaded (idle) site waits for its restore, and the memory unloading gives
# back (docs/BENCHMARK-HISTORY.md, "Idle sites leave memory", issue 34 item 4).
#
#   scripts/unload_time.sh out/restart27/data      # a store an `evermap-demo load` run left
#
# Works on a copy (the original is never opened): serves every site in it with
# `site_unload_after_s = UNLOAD_S` and the console on loopback, then CYCLES times: waits until
# /metrics says every site is unloaded (and 2 s more for the freed pages to go back), notes the
# server's RSS, asks each site's /api/sites/<site>/versions — which waits for the site's restore — and
# prints the answer's wall time and the RSS after it. Then the server's restore lines and /metrics'
# unload figures. Environment: BIN (default target/release/evermap-server; build it with
# `cargo build --release --workspace`), OUT (default out/unload_time), UNLOAD_S (default 5), CYCLES
# (default 5), HTTP_PORT (default 18080), PARALLEL (1: ask every site at once, not one after another),
# ASK (ask only the first ASK sites of the store each cycle; default all), IN_PLACE (1: serve the
# store itself, not a copy — for stores too big to copy, such as scripts/clone_sites.sh's; serving
# writes to it).
set -euo pipefail

STORE=${1:?usage: scripts/unload_time.sh STORE_DIR}
BIN=${BIN:-target/release/evermap-server}
OUT=${OUT:-out/unload_time}
UNLOAD_S=${UNLOAD_S:-5}
CYCLES=${CYCLES:-5}
HTTP_PORT=${HTTP_PORT:-18080}
TOKEN=unload-time-operator
# shellcheck source=serve_store.sh
source "$(dirname "$0")/serve_store.sh"
store_prepare "$STORE" "$OUT"
{
  printf 'listen = "127.0.0.1:0"\nmetrics_listen = "127.0.0.1:0"\nsite_unload_after_s = %s\n' "$UNLOAD_S"
  printf '[storage]\npath = "%s"\n[http]\nlisten = "127.0.0.1:%s"\noperator_token = "%s"\n' "$DATA" "$HTTP_PORT" "$TOKEN"
} >"$OUT/serve.toml"
store_site_entries unload-robot >>"$OUT/serve.toml"

ASKED=$(head -n "${ASK:-$n}" <<<"$SITES")
start=$(date +%s.%N)
store_serve "$OUT/serve.toml" "$OUT/serve.log"
rss_mib() { awk '/^VmRSS/ { printf "%.1f", $2 / 1024 }' "/proc/$pid/status"; }
get() { curl -sf -H "Authorization: Bearer $TOKEN" "http://127.0.0.1:$HTTP_PORT$1"; }
# Whether /metrics says every site is unloaded (read whole first: `grep -q` on a pipe may cut curl off).
all_unloaded() { local m; m=$(get /metrics) || return 1; grep -qx "evermap_sites_unloaded $n" <<<"$m"; }
store_wait_for "web console serving"
echo "$n site(s) served after $(echo "$(date +%s.%N) - $start" | bc) s (the console up): RSS $(rss_mib) MiB, $(get /metrics | grep -x 'evermap_sites_unloaded [0-9]*') at the start"
for cycle in $(seq 1 "$CYCLES"); do
  for _ in $(seq 1 600); do
    all_unloaded && break
    sleep 0.5
  done
  all_unloaded || { echo "not every site unloaded" >&2; exit 1; }
  sleep 2
  unloaded=$(rss_mib)
  if [ "${PARALLEL:-0}" = 1 ]; then
    # Every site asked at once: the restores share the cores.
    curls=()
    for site in $ASKED; do
      curl -sf -o "$OUT/answer-$site" -w '%{time_total}\n' -H "Authorization: Bearer $TOKEN" \
        "http://127.0.0.1:$HTTP_PORT/api/sites/$site/versions" >"$OUT/time-$site" &
      curls+=($!)
    done
    wait "${curls[@]}"
    for site in $ASKED; do
      echo "cycle $cycle: site $site unloaded (all at RSS $unloaded MiB); asked with the others, answered after $(cat "$OUT/time-$site") s"
    done
    echo "cycle $cycle: RSS $(rss_mib) MiB with every site restored"
  else
    for site in $ASKED; do
      t=$(curl -sf -o /dev/null -w '%{time_total}' -H "Authorization: Bearer $TOKEN" \
        "http://127.0.0.1:$HTTP_PORT/api/sites/$site/versions")
      echo "cycle $cycle: site $site unloaded at RSS $unloaded MiB; its versions answered after $t s; RSS $(rss_mib) MiB"
    done
  fi
done
sed 's/\x1b\[[0-9;]*m//g' "$OUT/serve.log" | grep -E "site log replayed|site unloaded|unloaded site restored" | sed 's/.*site=/  site=/'
metrics=$(get /metrics)
grep -E "^evermap_site(s_loaded|s_unloaded|_unloads_total|_restore_seconds)" <<<"$metrics"
store_stop
