# Sourced by the scripts that serve a store an `evermap-demo load` run left (restart_time.sh,
# unload_time.sh): the checks, the copy, the site list and the server's start, written once.
#
#   source "$(dirname "$0")/serve_store.sh"
#   store_prepare STORE OUT     # sets DATA (the store served: a copy under OUT, or STORE itself with
#                               # IN_PLACE=1), SITES (one id per line) and n (their count)
#   store_site_entries ROBOT    # appends a [[sites]] entry per site, one made-up robot each, to stdout
#   store_serve CONFIG LOG      # starts `$BIN serve` in the background: sets pid, kills it on exit
#   store_wait_for PATTERN      # waits (bounded: an hour) until LOG holds PATTERN; fails if the server exits
#   store_stop                  # SIGTERM, wait, and the exit trap removed
#
# Needs BIN (the evermap-server binary) set by the caller.

store_prepare() {
  local store=$1 out=$2
  [ -x "$BIN" ] || { echo "$BIN is missing: cargo build --release --workspace" >&2; exit 1; }
  [ -d "$store" ] || { echo "no store at $store" >&2; exit 1; }
  rm -rf "$out" && mkdir -p "$out"
  if [ "${IN_PLACE:-0}" = 1 ]; then
    DATA=$(cd "$store" && pwd)
  else
    cp -r "$store" "$out/data"
    DATA=$(cd "$out/data" && pwd)
  fi
  printf 'listen = "127.0.0.1:0"\nmetrics_listen = "127.0.0.1:0"\n[storage]\npath = "%s"\n' "$DATA" >"$out/list.toml"
  SITES=$("$BIN" site list --config "$out/list.toml" | cut -f1)
  [ -n "$SITES" ] || { echo "the store at $store holds no site" >&2; exit 1; }
  n=$(wc -l <<<"$SITES")
}

store_site_entries() {
  local robot=$1 k=0 site
  for site in $SITES; do
    k=$((k + 1))
    printf '\n[[sites]]\nid = "%s"\nrobots = [{ id = "%s", token = "%s-token-%d" }]\n' "$site" "$robot" "$robot" "$k"
  done
}

store_serve() {
  STORE_LOG=$2
  NO_COLOR=1 RUST_LOG=${RUST_LOG:-info} "$BIN" serve --config "$1" >"$STORE_LOG" 2>&1 &
  pid=$!
  trap 'kill -TERM $pid 2>/dev/null || true' EXIT
}

store_wait_for() {
  local _
  for _ in $(seq 1 18000); do
    grep -q "$1" "$STORE_LOG" && return 0
    kill -0 "$pid" 2>/dev/null || { echo "the server exited:" >&2; tail -20 "$STORE_LOG" >&2; exit 1; }
    sleep 0.2
  done
  echo "no \"$1\" after an hour" >&2
  exit 1
}

store_stop() {
  kill -TERM "$pid"
  wait "$pid"
  trap - EXIT
}
