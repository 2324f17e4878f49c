#!/usr/bin/env python3
"""When each later session of an `evermap-agent sessions` run reaches mapped ground, against when it was
placed and committed (issue 33's target counts from that moment), and how long it drove on mapped ground
before its commit.

A later session is on ground an earlier session mapped at its scans tied by a ground-truth relation to a
scan of an earlier session that is in the map (session 0, or a later one that was committed: a session
dropped on probation is not), counting only scans more than MARGIN s into the session (its first seconds
hold the one relation across the cut, the robot still where the previous session ended). It reaches
mapped ground at the first such scan; the time on mapped ground is the length of the union of WINDOW s
either side of each such scan (relations are sampled about once a second where sessions overlap), from
MARGIN s into the session to its commit, or to its end when it is never committed: a lower bound, since
the relations leave stretches of mapped ground unsampled (Intel's more than the others). An analysis until
`sessions` reports it from its own scoring.

    python3 scripts/mapped_ground.py OUT_DIR ../shared/datasets/relations/REC.relations [--margin 5] [--window 2.5]
"""
import argparse
import json


def union_length(intervals, lo, hi):
    """Length of the union of `intervals` clipped to [lo, hi]."""
    total, end = 0.0, lo
    for a, b in sorted(intervals):
        a, b = max(a, end), min(b, hi)
        if b > a:
            total += b - a
            end = b
    return total


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="the `sessions` output folder (its report.json)")
    parser.add_argument("relations")
    parser.add_argument("--margin", type=float, default=5.0, help="seconds into a session not counted")
    parser.add_argument("--window", type=float, default=2.5, help="seconds either side of a relation on mapped ground")
    args = parser.parse_args()
    report = json.load(open(f"{args.run}/report.json"))
    starts = [s["start_time"] / 1e9 for s in report["sessions"]]
    scores = report["session_scores"]
    in_map = [k == 0 or scores[k]["committed_after_s"] is not None for k in range(len(starts))]
    last_stamp = 0.0

    def session_of(t):
        return max((i for i, s in enumerate(starts) if t >= s), default=0)

    on_ground = {}
    for line in open(args.relations):
        fields = line.split()
        if len(fields) < 2:
            continue
        earlier, later = sorted((float(fields[0]), float(fields[1])))
        last_stamp = max(last_stamp, later)
        s_earlier, s_later = session_of(earlier), session_of(later)
        into = later - starts[s_later]
        if s_earlier == s_later or into <= args.margin or not in_map[s_earlier]:
            continue
        on_ground.setdefault(s_later, []).append(into)
    print(
        "session  relations  mapped ground at (s)  placed at (s)  committed at (s)  committed after it (s)"
        "  on mapped ground before commit (s)"
    )
    for k, score in enumerate(scores[1:], start=1):
        stamps = on_ground.get(k, [])
        first = min(stamps, default=None)
        placed, committed = score["placed_after_s"], score["committed_after_s"]
        after = committed - first if first is not None and committed is not None else None
        end = starts[k + 1] - starts[k] if k + 1 < len(starts) else last_stamp - starts[k]
        driven = union_length(
            [(t - args.window, t + args.window) for t in stamps],
            args.margin,
            committed if committed is not None else end,
        )

        def show(x):
            return "never" if x is None else f"{x:.1f}"

        print(
            f"{k:7d}  {len(stamps):9d}  {show(first) if stamps else '-':>20}  {show(placed):>13}  "
            f"{show(committed):>16}  {show(after) if stamps else '-':>22}  "
            f"{(f'{driven:.1f}' + ('' if committed is not None else ' (never committed)')) if stamps else '-':>34}"
        )


if __name__ == "__main__":
    main()
