#!/usr/bin/env python3
"""When each later session of an `evermap-agent sessions` run reaches mapped ground, against when it was
placed and committed (issue 33's target counts from that moment).

A later session reaches ground an earlier session mapped at its first scan tied by a ground-truth relation
to a scan of an earlier session, counting only scans more than MARGIN s into the session (its first
seconds hold the one relation across the cut, the robot still where the previous session ended). An
analysis until `sessions` reports it from its own scoring: it does not know whether the earlier session
is in the map (a session dropped on probation is not).

    python3 scripts/mapped_ground.py OUT_DIR ../shared/datasets/relations/REC.relations [--margin 5]
"""
import argparse
import json


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", help="the `sessions` output folder (its report.json)")
    parser.add_argument("relations")
    parser.add_argument("--margin", type=float, default=5.0, help="seconds into a session not counted")
    args = parser.parse_args()
    report = json.load(open(f"{args.run}/report.json"))
    starts = [s["start_time"] / 1e9 for s in report["sessions"]]

    def session_of(t):
        return max((i for i, s in enumerate(starts) if t >= s), default=0)

    reached = {}
    for line in open(args.relations):
        fields = line.split()
        if len(fields) < 2:
            continue
        earlier, later = sorted((float(fields[0]), float(fields[1])))
        s_earlier, s_later = session_of(earlier), session_of(later)
        into = later - starts[s_later]
        if s_earlier == s_later or into <= args.margin:
            continue
        first, count = reached.get(s_later, (into, 0))
        reached[s_later] = (min(first, into), count + 1)
    print("session  relations  mapped ground at (s)  placed at (s)  committed at (s)  committed after it (s)")
    for k, score in enumerate(report["session_scores"][1:], start=1):
        first, count = reached.get(k, (None, 0))
        placed, committed = score["placed_after_s"], score["committed_after_s"]
        after = committed - first if first is not None and committed is not None else None

        def show(x):
            return "never" if x is None else f"{x:.1f}"

        print(
            f"{k:7d}  {count:9d}  {show(first) if count else '-':>20}  {show(placed):>13}  "
            f"{show(committed):>16}  {show(after) if count else '-':>22}"
        )


if __name__ == "__main__":
    main()
