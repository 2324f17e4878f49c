#!/usr/bin/env python3
"""Trajectories scored on the relations whose two stamps are both scans of the first one, and its tears.

    relations_at_scans.py RELATIONS TRAJ [TRAJ ...] [--torn-deg D --max-span S]

Each TRAJ is a TUM file (`t x y z qx qy qz qw`, as `offline` and `sessions` write). The relations kept
are those whose stamps both have a pose of the FIRST trajectory within 1 ms (the relation's own scans,
as `relations_at_scans` of report.json takes them); every trajectory is scored on that same set, so a run
with scans dropped (`--perturb slow`) can be set beside the clean run. With --torn-deg, also lists the
start times (seconds from the first trajectory's first stamp) of relations shorter than --max-span
seconds whose rotation error in the first trajectory exceeds D degrees: where it tears.
"""
import argparse
import bisect
import math

SCAN_STAMP_TOLERANCE_S = 0.001


def load(path):
    rows = [tuple(map(float, line.split())) for line in open(path) if line.strip() and not line.startswith("#")]
    return [r[0] for r in rows], rows


def at(stamps, rows, t, tolerance):
    i = bisect.bisect_left(stamps, t)
    near = [j for j in (i - 1, i) if 0 <= j < len(stamps)]
    if not near:
        return None
    j = min(near, key=lambda k: abs(stamps[k] - t))
    return rows[j] if abs(stamps[j] - t) <= tolerance else None


def heading(r):
    return 2.0 * math.atan2(r[6], r[7])


def error(a, b, rel):
    dx, dy = b[1] - a[1], b[2] - a[2]
    c, s = math.cos(heading(a)), math.sin(heading(a))
    ex, ey = c * dx + s * dy - rel[2], -s * dx + c * dy - rel[3]
    dth = (heading(b) - heading(a) - rel[7] + math.pi) % (2.0 * math.pi) - math.pi
    return math.hypot(ex, ey), abs(math.degrees(dth))


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("relations")
    parser.add_argument("trajectories", nargs="+")
    parser.add_argument("--torn-deg", type=float)
    parser.add_argument("--max-span", type=float, default=20.0)
    args = parser.parse_args()
    relations = [list(map(float, line.split())) for line in open(args.relations) if line.strip()]
    first = load(args.trajectories[0])
    kept = [r for r in relations
            if at(*first, r[0], SCAN_STAMP_TOLERANCE_S) and at(*first, r[1], SCAN_STAMP_TOLERANCE_S)]
    print(f"{len(kept)} of {len(relations)} relations have both stamps on scans of {args.trajectories[0]}")
    for path in args.trajectories:
        traj = load(path)
        errors = []
        for r in kept:
            a, b = at(*traj, r[0], 0.1), at(*traj, r[1], 0.1)
            if a and b:
                errors.append(error(a, b, r))
        n = len(errors)
        if n:
            print(f"{path}: {n} relations, {sum(e[0] for e in errors) / n:.4f} m / "
                  f"{sum(e[1] for e in errors) / n:.3f} deg mean, largest {max(e[0] for e in errors):.2f} m")
    if args.torn_deg is not None:
        start = first[0][0]
        torn = sorted({round(r[0] - start) for r in relations
                       if abs(r[1] - r[0]) < args.max_span
                       and (a := at(*first, r[0], 0.1)) and (b := at(*first, r[1], 0.1))
                       and error(a, b, r)[1] > args.torn_deg})
        print(f"relations under {args.max_span} s torn over {args.torn_deg} deg start at (s): {torn}")


if __name__ == "__main__":
    main()
