#!/usr/bin/env python3
"""The robustness suite over several perturbation seeds: one row per variant, one column per recording.

A random variant (`hard`, `slip`, `clutter`, ...) is one draw of its perturbation; its seed-1 cell says
little about the next draw. For each cell over OUT_DIR/seed*/REC/VARIANT/report.json (what
`SEEDS="1 2 3" scripts/robustness_suite.sh OUT_DIR` writes): the median and the worst mean translational
relation error (m) over the seeds, the largest relation error of any seed (m), and how many seeds break a
bound of issue 32 (a relation over 1 m; a mean over 0.10 m, `hard` 0.15 m). Every variant is scored on all
its relations, as robustness_table.py scores all but `slow` and `thin`.  Usage: robustness_seeds.py OUT_DIR
"""
import json
import statistics
import sys
from pathlib import Path

from robustness_table import ORDER, breaks_bound


def main() -> int:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/robustness")
    runs = {}
    for path in sorted(out.glob("seed*/*/*/report.json")):
        rec, variant = path.parent.parent.name, path.parent.name
        rel = json.loads(path.read_text())["relations"]
        runs.setdefault((rec, variant), []).append((rel["trans_abs_mean_m"], rel["trans_abs_max_m"]))
    if not runs:
        print(f"no reports under {out}/seed*/", file=sys.stderr)
        return 1
    recordings = sorted({r for r, _ in runs})
    found = {v for _, v in runs}
    variants = [v for v in ORDER if v in found] + sorted(found - set(ORDER))
    print("| variant | " + " | ".join(recordings) + " |")
    print("|---" * (len(recordings) + 1) + "|")
    for v in variants:
        cells = []
        for r in recordings:
            seeds = runs.get((r, v), [])
            if not seeds:
                cells.append("")
                continue
            means = [m for m, _ in seeds]
            broken = sum(breaks_bound(v, m, x, None) for m, x in seeds)
            verdict = f"{broken} of {len(seeds)} ✘" if broken else "✔"
            cells.append(f"{statistics.median(means):.3f} / {max(means):.3f} "
                         f"({max(x for _, x in seeds):.2f}) {verdict}")
        print(f"| {v} | " + " | ".join(cells) + " |")
    print("\ncells: median / worst mean (m) over the seeds (largest relation of any seed, m), seeds breaking a bound",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
