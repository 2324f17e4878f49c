#!/usr/bin/env python3
"""The robustness suite's table: one row per variant, one column per recording.

Each cell: mean translational relation error (m), and in brackets the largest relation error (m) and
the number of relations torn (over 0.3 m or 3 degrees). A cell is marked ✘ where it breaks a bound of
issue 32: a relation over 1 m; a mean over 0.10 m (hard: 0.15 m); for a mild variant, a mean over twice
the clean run's. `slow` (scans at least 0.7 s apart) and `thin` (`sparse` + `slow`) are scored on the scans the engine had
(`relations_at_scans` of report.json: relations whose two stamps both have a scan), since at the stamps it
has no scan for, the interpolated pose's own error is a floor no engine goes below; the cell names the
relations scored. The combined rows (`range4,odom`, `range4,slip`, `range4,lag`: a 4-m scanner with one
odometry fault each) are judged by the general bounds.  Usage: robustness_table.py OUT_DIR
"""
import json
import sys
from pathlib import Path

MILD = {"range8", "sparse", "odom", "slow", "clutter", "late", "noise", "stall", "lag", "burst", "scanburst", "clock", "dense"}
ORDER = ["clean", "range8", "range4", "sparse", "odom", "slip", "slow", "clutter", "late", "noise", "stall", "hard", "thin", "lag", "burst", "scanburst", "clock", "dense", "range4,odom", "range4,slip", "range4,lag", "range4,clock"]
AT_SCANS = {"slow", "thin"}


def breaks_bound(variant: str, mean: float, worst: float, clean_mean: float | None) -> bool:
    """Whether a run breaks a bound of issue 32: a relation over 1 m; a mean over 0.10 m (`hard` 0.15 m);
    for a mild variant with its clean run's mean given, a mean over twice that."""
    ok = worst <= 1.0 and mean <= (0.15 if variant == "hard" else 0.10)
    if variant in MILD and clean_mean is not None:
        ok = ok and mean <= 2.0 * clean_mean
    return not ok


def main() -> int:
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "out/robustness")
    reports = {}
    for path in sorted(out.glob("*/*/report.json")):
        rec, variant = path.parent.parent.name, path.parent.name
        reports[(rec, variant)] = json.loads(path.read_text())
    if not reports:
        print(f"no reports under {out}", file=sys.stderr)
        return 1
    recordings = sorted({r for r, _ in reports})
    variants = [v for v in ORDER if any(v == w for _, w in reports)]
    variants += sorted({w for _, w in reports} - set(ORDER))
    failures = 0
    header = "| variant | " + " | ".join(recordings) + " |"
    print(header)
    print("|---" * (len(recordings) + 1) + "|")
    for v in variants:
        cells = []
        for r in recordings:
            rep = reports.get((r, v))
            if rep is None:
                cells.append("")
                continue
            at_scans = v in AT_SCANS and rep.get("relations_at_scans") is not None
            rel = rep["relations_at_scans"] if at_scans else rep["relations"]
            mean, worst, torn = rel["trans_abs_mean_m"], rel["trans_abs_max_m"], rel["torn"]
            clean = reports.get((r, "clean"))
            ok = not breaks_bound(v, mean, worst, clean and clean["relations"]["trans_abs_mean_m"])
            failures += not ok
            speed = rep.get("realtime_factor", 0.0)
            scored = f", {rel['count']} at scans" if at_scans else ""
            cells.append(
                f"{mean:.4f} / {rel['rot_abs_mean_deg']:.3f}° ({worst:.2f}, {torn} torn{scored}) {speed:.0f}× {'✔' if ok else '✘'}"
            )
        print(f"| {v} | " + " | ".join(cells) + " |")
    print(f"\n{failures} cells break a bound", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
