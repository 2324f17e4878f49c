#!/usr/bin/env python3
"""Relations error of a TUM trajectory over all relations and over those whose two stamps fall in different
equal time spans of the trajectory (what `evermap-agent sessions --split N` calls cross-session relations),
so a single-session `offline` run can be compared with a multi-session run on the same subsets.
Same metric as mapping::metrics::relations_metric (nearest pose within 0.1 s, component-wise error).
With --sessions-report (a `sessions` run's report.json), the sessions are that run's (its start times) and
relations touching a session it dropped (never placed or never committed) are left out, as `sessions`
scores its own `relations_cross_session`.

    python3 scripts/relations_by_session.py out/intel/trajectory.tum ../shared/datasets/relations/intel.relations --split 3
    python3 scripts/relations_by_session.py out/intel/trajectory.tum ../shared/datasets/relations/intel.relations \
        --sessions-report out/sessions/intel-3/report.json
"""
import argparse
import bisect
import json
import math
import statistics


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("trajectory")
    parser.add_argument("relations")
    parser.add_argument("--split", type=int, default=3)
    parser.add_argument("--sessions-report", help="a `sessions` run's report.json: its sessions, its dropped ones left out")
    args = parser.parse_args()
    rows = [
        list(map(float, line.split()))
        for line in open(args.trajectory)
        if line.strip() and not line.startswith("#")
    ]
    stamps = [r[0] for r in rows]
    poses = [(r[1], r[2], 2 * math.atan2(r[6], r[7])) for r in rows]

    def nearest(t):
        i = bisect.bisect_left(stamps, t)
        k = min((k for k in (i - 1, i) if 0 <= k < len(stamps)), key=lambda k: abs(stamps[k] - t))
        return k if abs(stamps[k] - t) <= 0.1 else None

    span = (stamps[-1] - stamps[0]) / args.split

    def part(t):
        return min(args.split - 1, int((t - stamps[0]) / span))

    kept = None
    if args.sessions_report:
        report = json.load(open(args.sessions_report))
        starts = [s["start_time"] / 1e9 for s in report["sessions"]]
        kept = {s["session"] for s in report["sessions"] if s["placed"]}

        def part(t):  # noqa: F811 (the run's own sessions)
            return max(0, bisect.bisect_right(starts, t) - 1)

    subsets = {"all": ([], []), "cross_session": ([], [])}
    for line in open(args.relations):
        if not line.strip():
            continue
        t1, t2, x, y, _, _, _, yaw = map(float, line.split()[:8])
        a, b = nearest(t1), nearest(t2)
        if a is None or b is None:
            continue
        if kept is not None and part(t1) != part(t2) and not (part(t1) in kept and part(t2) in kept):
            continue
        xa, ya, tha = poses[a]
        xb, yb, thb = poses[b]
        dx, dy = xb - xa, yb - ya
        ex = math.cos(tha) * dx + math.sin(tha) * dy
        ey = -math.sin(tha) * dx + math.cos(tha) * dy
        trans = math.hypot(ex - x, ey - y)
        rot = abs(math.degrees(wrap(wrap(thb - tha) - yaw)))
        keys = ["all"] + (["cross_session"] if part(t1) != part(t2) else [])
        for key in keys:
            subsets[key][0].append(trans)
            subsets[key][1].append(rot)
    for key, (trans, rot) in subsets.items():
        if not trans:
            print(f"{key}: no relations")
            continue
        print(
            f"{key}: count {len(trans)}, trans mean {statistics.fmean(trans):.4f} m median "
            f"{statistics.median(trans):.4f} m, rot mean {statistics.fmean(rot):.3f} deg median "
            f"{statistics.median(rot):.3f} deg"
        )


if __name__ == "__main__":
    main()
