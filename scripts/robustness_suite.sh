#!/usr/bin/env bash
# The robustness suite: every variant of `evermap-agent offline --perturb` on the Freiburg recordings,
# scored against their relations, and one table of the results (scripts/robustness_table.py).
#
#   scripts/robustness_suite.sh [OUT_DIR]        (default out/robustness)
#   SEEDS="1 2 3 4 5 6" VARIANTS=hard scripts/robustness_suite.sh OUT_DIR
#                                                (each seed in OUT_DIR/seedN, then scripts/robustness_seeds.py)
#
# Environment: RECORDINGS (default "mit-csail aces intel"), VARIANTS (default: every variant),
# CONFIG (a TOML file passed as --config; the suite's figures are scored without one), SEED (default 1),
# SEEDS (several perturbation seeds: a random variant's one draw says little about the next), JOBS
# (parallel runs, default 2), AGENT (default target/release/evermap-agent), REFERENCE (a suite's
# OUT_DIR whose REC/clean/trajectory.tum judges each GLM match of the other variants, default OUT_DIR:
# the clean runs go first; scripts/glm_rules_table.py OUT_DIR tabulates the judged matches).
# A run whose report.json exists is not run again, so an interrupted suite resumes where it stopped;
# delete OUT_DIR to start over (do so after changing the engine).
set -euo pipefail
self=$(realpath "$0")
cd "$(dirname "$0")/.."
out=${1:-out/robustness}
if [[ -n ${SEEDS:-} && $(wc -w <<<"$SEEDS") -gt 1 ]]; then
  for s in $SEEDS; do
    SEEDS= SEED=$s "$self" "$out/seed$s" >/dev/null
  done
  exec python3 scripts/robustness_seeds.py "$out"
fi
recordings=${RECORDINGS:-"mit-csail aces intel"}
variants=${VARIANTS:-"clean range8 range4 sparse odom slip slow clutter late noise stall hard thin lag burst scanburst clock dense range4,odom range4,slip range4,lag range4,clock"}
seed=${SEED:-1}
jobs=${JOBS:-2}
agent=${AGENT:-target/release/evermap-agent}
datasets=../shared/datasets
if [[ ! -x $agent ]]; then
  echo "no $agent: build it first (cargo build --release --workspace)" >&2
  exit 1
fi
mkdir -p "$out"
runs=()
for r in $recordings; do
  for v in $variants; do
    [[ -f $out/$r/$v/report.json ]] || runs+=("$r $v")
  done
done
echo "${#runs[@]} runs to do in $out (seed $seed, $jobs at a time)" >&2
run_one() {
  local r=$1 v=$2 dir=$out/$1/$2
  mkdir -p "$dir"
  local reference=$reference_dir/$r/clean/trajectory.tum
  [[ $v != clean && -f $reference ]] || reference=
  if "$agent" offline --input "$datasets/rosbag1/$r.orig.bag" --relations "$datasets/relations/$r.relations" \
      --perturb "$v" --perturb-seed "$seed" ${config:+--config "$config"} ${reference:+--reference-trajectory "$reference"} \
      --out "$dir.partial" >"$dir/stdout" 2>"$dir/stderr"; then
    mv "$dir.partial"/* "$dir"/ && rmdir "$dir.partial"
    echo "done $r $v" >&2
  else
    echo "FAILED $r $v (see $dir/stderr)" >&2
  fi
}
export -f run_one
config=${CONFIG:-}
reference_dir=${REFERENCE:-$out}
export out seed agent datasets config reference_dir
# The clean runs first: each is the reference its recording's other variants judge their matches by.
for phase in clean other; do
  for run in "${runs[@]}"; do
    variant=${run#* }
    if [[ ($phase == clean && $variant == clean) || ($phase != clean && $variant != clean) ]]; then
      echo "$run"
    fi
  done | xargs -r -P "$jobs" -L 1 bash -c 'run_one $0 $1'
done
python3 scripts/robustness_table.py "$out"
