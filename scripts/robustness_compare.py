#!/usr/bin/env python3
"""A change judged on the robustness suite: issue 32's keep rule, on one draw of each engine or on several.

BEFORE and AFTER are suite directories (REC/VARIANT/report.json, what robustness_suite.sh writes) of two
engines on the same perturbation seed. Either side may list several directories, comma-separated: the
same engine drawn again. The engine is chaotic where a decision sits on a threshold (a match accepted or
refused, a loop closed or not), so a change that means nothing physically redraws such cells as much as a
real change does: a loop closure's σ 0.3 % larger (`[global.constraint_builder]
loop_closure_translation_sigma = 0.0301`, or `loop_closure_rotation_sigma = 0.01003`), or a weight of LLO's
least squares 0.3 % larger (`[local.least_squares] translation_weight = 3.009`, or `rotation_weight =
10.03`). Running each engine with such null changes too gives each cell a few draws (BENCHMARKS.md, "Session
82").

Per cell and side: the median over the side's draws of the mean translational relation error (m), the
largest relation of any draw (m), and how many draws break a bound of issue 32 (a relation over 1 m; a mean
over 0.10 m, `hard` 0.15 m; a mild variant over twice its clean run). Cells are scored as
robustness_table.py scores them (`slow` and `thin` on the relations at the scans). The keep rule (issue
32, item 3) breaks where AFTER's median is more than 5 % worse than BEFORE's, or where more of AFTER's draws
than BEFORE's have a relation over 1 m. With one directory a side, that is the rule on one draw.

The same engine's draws split in two halves break this rule too (session 83: 11 and 15 of 63 cells with two
draws a side, and one-draw differences of a cell's count of relations over 1 m in four cells), so the totals
over the suite are printed beside it: the draws over a bound and the draws with a relation over 1 m. With
several draws a side, each cell also counts AFTER's draws more than 5 % worse than BEFORE's median: a cell
whose every draw is (a regression the draws agree on) is counted apart from the medians' rule, if at least
two of those draws differ (a null change that touches nothing the cell decides, such as a loop closure's σ
where no loop closes, draws the same run again: session 84).

Either side's entries may also be draw files (JSON, a few kilobytes: each cell's scored mean and largest
relation) that `--save` writes from a suite directory, so that a draw outlives the machine it ran on; the
current engine's draws are kept in docs/robustness/.

Usage: robustness_compare.py BEFORE[,BEFORE...] AFTER[,AFTER...]   (cells that keep the rule are listed
too; the totals go to standard error)
       robustness_compare.py --save SUITE_DIR DRAW.json
"""
import json
import statistics
import sys
from pathlib import Path

from robustness_table import AT_SCANS, breaks_bound


def scored(out: Path) -> dict:
    """Each cell's scored relations (mean and largest translational error, m) of a suite directory, or of
    a draw file that `--save` wrote from one."""
    if out.is_file():
        draw = json.loads(out.read_text())
        return {tuple(key.split("/", 1)): (cell["trans_abs_mean_m"], cell["trans_abs_max_m"]) for key, cell in draw.items()}
    cells = {}
    for path in sorted(out.glob("*/*/report.json")):
        rec, variant = path.parent.parent.name, path.parent.name
        rep = json.loads(path.read_text())
        at_scans = variant in AT_SCANS and rep.get("relations_at_scans") is not None
        rel = rep["relations_at_scans"] if at_scans else rep["relations"]
        cells[(rec, variant)] = (rel["trans_abs_mean_m"], rel["trans_abs_max_m"])
    return cells


def save(out: Path, draw: Path) -> int:
    """Writes the scored cells of suite directory OUT as a draw file: the suite's runs are large and live
    on one machine, the draw a later comparison needs is a few kilobytes kept in the repository."""
    cells = scored(out)
    if not cells:
        print(f"no reports under {out}", file=sys.stderr)
        return 1
    draw.write_text(json.dumps(
        {f"{rec}/{variant}": {"trans_abs_mean_m": mean, "trans_abs_max_m": worst}
         for (rec, variant), (mean, worst) in sorted(cells.items())},
        indent=1,
    ) + "\n")
    return 0


def load(out: Path) -> dict:
    cells = scored(out)
    return {
        (rec, variant): (mean, worst, breaks_bound(variant, mean, worst, cells.get((rec, "clean"), (None,))[0]))
        for (rec, variant), (mean, worst) in cells.items()
    }


def side(dirs: str) -> list:
    draws = [load(Path(d)) for d in dirs.split(",") if d]
    if not draws or not all(draws):
        raise SystemExit(f"no reports under one of {dirs}")
    return draws


def summary(draws: list, cell: tuple) -> tuple:
    runs = [d[cell] for d in draws]
    return (
        statistics.median(r[0] for r in runs),
        max(r[1] for r in runs),
        sum(r[1] > 1.0 for r in runs),
        sum(r[2] for r in runs),
        [r[0] for r in runs],
    )


def main() -> int:
    if len(sys.argv) == 4 and sys.argv[1] == "--save":
        return save(Path(sys.argv[2]), Path(sys.argv[3]))
    if len(sys.argv) != 3:
        print(__doc__, file=sys.stderr)
        return 2
    before, after = side(sys.argv[1]), side(sys.argv[2])
    cells = set.intersection(*(set(d) for d in before + after))
    if not cells:
        print("no cell in every directory", file=sys.stderr)
        return 1
    broken = broken_every_draw = over_before = over_after = torn_before = torn_after = 0
    print(
        f"| recording | variant | before (m, median of {len(before)}) | after (m, median of {len(after)}) | change "
        "| largest before / after (m) | draws over a bound before / after | after's draws 5 % worse than before's "
        "median | keep rule |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for cell in sorted(cells):
        b_mean, b_max, b_torn, b_over, _ = summary(before, cell)
        a_mean, a_max, a_torn, a_over, a_runs = summary(after, cell)
        breaks = a_mean > 1.05 * b_mean or a_torn > b_torn
        broken += breaks
        worse = sum(m > 1.05 * b_mean for m in a_runs)
        distinct = len(set(a_runs))
        every_draw_worse = distinct > 1 and worse == len(a_runs)
        broken_every_draw += every_draw_worse
        over_before += b_over
        over_after += a_over
        torn_before += b_torn
        torn_after += a_torn
        print(
            f"| {cell[0]} | {cell[1]} | {b_mean:.4f} | {a_mean:.4f} | {(a_mean / b_mean - 1.0) * 100.0:+.1f} % "
            f"| {b_max:.2f} / {a_max:.2f} | {b_over} / {a_over} | {worse} of {len(a_runs)} ({distinct} distinct) "
            f"| {'breaks' if breaks else 'keeps'} |"
        )
    print(
        f"\n{len(cells)} cells, {len(before)} / {len(after)} draws; draws over a bound before {over_before}, "
        f"after {over_after}; draws with a relation over 1 m before {torn_before}, after {torn_after}; "
        f"keep rule broken in {broken} cells; every one of several (at least two distinct) draws 5 % worse than "
        f"before's median in {broken_every_draw} cells",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
