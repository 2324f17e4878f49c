#!/usr/bin/env bash
# A store of many sites made of copies of a few mapped ones (docs/BENCHMARK-HISTORY.md, "Idle sites leave memory":
# one instance holding 500 sites, issue 34).
#
#   scripts/clone_sites.sh out/sites5/data 500 out/sites500/data   # a store an `evermap-demo load` run left
#
# Exports every site of SOURCE (never written: the exports read a copy) with `evermap-server site
# export`, then imports them round-robin into the new store DEST under the ids `<site>-c0001`,
# `<site>-c0002`, ... until it holds COUNT sites (1..=2000), with `evermap-server site import`. Each copy
# is the whole site: its checkpoints, its log after the older one, its versions and sessions. DEST
# must not exist. Environment: BIN (default target/release/evermap-server; build it with
# `cargo build --release --workspace`), WORK (default DEST's parent/clone_work: the copy and the
# archives, deleted at the end).
set -euo pipefail

SOURCE=${1:?usage: scripts/clone_sites.sh SOURCE_STORE COUNT DEST_STORE}
COUNT=${2:?usage: scripts/clone_sites.sh SOURCE_STORE COUNT DEST_STORE}
DEST=${3:?usage: scripts/clone_sites.sh SOURCE_STORE COUNT DEST_STORE}
BIN=${BIN:-target/release/evermap-server}
[ -x "$BIN" ] || { echo "$BIN is missing: cargo build --release --workspace" >&2; exit 1; }
[ -d "$SOURCE" ] || { echo "no store at $SOURCE" >&2; exit 1; }
[[ "$COUNT" =~ ^[0-9]+$ ]] && [ "$COUNT" -ge 1 ] && [ "$COUNT" -le 2000 ] \
  || { echo "COUNT must be 1..=2000, not $COUNT" >&2; exit 1; }
[ -e "$DEST" ] && { echo "$DEST exists: give a new path" >&2; exit 1; }
WORK=${WORK:-$(dirname "$DEST")/clone_work}

rm -rf "$WORK" && mkdir -p "$WORK/archives" "$(dirname "$DEST")"
cp -r "$SOURCE" "$WORK/source"
printf '[storage]\npath = "%s"\n' "$(cd "$WORK/source" && pwd)" >"$WORK/source.toml"
mkdir -p "$DEST"
printf '[storage]\npath = "%s"\n' "$(cd "$DEST" && pwd)" >"$WORK/dest.toml"
mapfile -t SITES < <("$BIN" site list --config "$WORK/source.toml" | cut -f1)
[ "${#SITES[@]}" -gt 0 ] || { echo "the store at $SOURCE holds no site" >&2; exit 1; }
for site in "${SITES[@]}"; do
  "$BIN" site export --config "$WORK/source.toml" --site "$site" --out "$WORK/archives/$site.evermap-site" >/dev/null
done
for k in $(seq 1 "$COUNT"); do
  site=${SITES[$(((k - 1) % ${#SITES[@]}))]}
  clone=$(printf '%s-c%04d' "$site" "$k")
  "$BIN" site import --config "$WORK/dest.toml" --site "$clone" --archive "$WORK/archives/$site.evermap-site" >/dev/null
  [ $((k % 50)) -eq 0 ] && echo "$k of $COUNT sites imported"
done
rm -rf "$WORK"
echo "$COUNT sites (copies of ${SITES[*]}) in $DEST: $(du -sh "$DEST" | cut -f1)"
