#!/usr/bin/env python3
"""One table of the real-recording session runs in a directory (scripts/real_sessions.sh OUT_DIR: each run in
OUT_DIR/R-N with its `evermap-agent sessions` report.json): per run, when each later session was placed and
committed (seconds after its start; `-` never), the placements acted on judged wrong, the cross-session
relations smoothed and at the time (mean m, with their count), and the wall time. With a second directory,
a last column says which runs' trajectory.tum differ from it byte for byte.

    python3 scripts/real_sessions_table.py out/sessions [REFERENCE_DIR]
"""
import filecmp
import json
import os
import sys


def seconds(value):
    return "-" if value is None else f"{value:.1f}"


def metres(stats):
    if not stats or not stats.get("count"):
        return "-"
    return f"{stats['trans_abs_mean_m']:.4f} ({stats['count']})"


def main():
    if len(sys.argv) not in (2, 3):
        sys.exit(__doc__)
    out = sys.argv[1]
    reference = sys.argv[2] if len(sys.argv) == 3 else None
    runs = sorted(
        d for d in os.listdir(out) if os.path.isfile(os.path.join(out, d, "report.json"))
    )
    if not runs:
        sys.exit(f"no run with a report.json in {out}")
    header = "| run | later sessions: placed / committed (s) | wrong placed / held | cross-session smoothed (m) | at the time (m) | dropped-session relations | wall (s) |"
    if reference:
        header += " trajectory vs reference |"
    print(header)
    print("|---" * (header.count("|") - 1) + "|")
    for run in runs:
        with open(os.path.join(out, run, "report.json")) as f:
            report = json.load(f)
        later = [s for s in report["session_scores"] if s["session"] > 0]
        times = ", ".join(
            f"{seconds(s['placed_after_s'])} / {seconds(s['committed_after_s'])}" for s in later
        )
        placements = report["placements"]
        wrong = f"{placements['placed']['wrong']} / {placements['held']['wrong']}"
        row = (
            f"| {run} | {times} | {wrong} | {metres(report['relations_cross_session'])} "
            f"| {metres(report['relations_cross_session_at_the_time'])} "
            f"| {report['relations_across_dropped_sessions']} | {report['wall_time_s']:.0f} |"
        )
        if reference:
            mine = os.path.join(out, run, "trajectory.tum")
            theirs = os.path.join(reference, run, "trajectory.tum")
            if not os.path.exists(theirs):
                verdict = "no reference"
            else:
                verdict = "identical" if filecmp.cmp(mine, theirs, shallow=False) else "differs"
            row += f" {verdict} |"
        print(row)


if __name__ == "__main__":
    main()
