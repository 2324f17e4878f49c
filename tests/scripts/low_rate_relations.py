"""Relations-style error of a run on a thinned recording against the full-rate run of the same engine.

The benchmark's relations name scans the thinned recording dropped, so for each relation (t1, t2) the
kept scans nearest t1 and t2 (within 0.36 s) are compared instead, and the reference relative pose is the
full-rate run's between those two scans (itself within a few centimetres of the relations).

    python3 tests/scripts/low_rate_relations.py FULL/trajectory.tum LOW/trajectory.tum RELATIONS
"""
import sys, math, bisect
def load(p):
    d = {}
    for l in open(p):
        f = l.split()
        t = float(f[0]); x, y = float(f[1]), float(f[2]); qz, qw = float(f[6]), float(f[7])
        d[round(t, 4)] = (x, y, 2 * math.atan2(qz, qw))
    return d
ref, est = load(sys.argv[1]), load(sys.argv[2])
keys = sorted(est)
def near(t):
    i = bisect.bisect_left(keys, t)
    c = [k for k in keys[max(0, i-1):i+1]]
    k = min(c, key=lambda k: abs(k - t))
    return k if abs(k - t) < 0.36 else None
def rel(a, b):
    dx, dy = b[0]-a[0], b[1]-a[1]; c, s = math.cos(a[2]), math.sin(a[2])
    return (c*dx + s*dy, -s*dx + c*dy, b[2]-a[2])
terr, rerr = [], []
seen = set()
for l in open(sys.argv[3]):
    f = l.split()
    if len(f) < 8: continue
    k1, k2 = near(float(f[0])), near(float(f[1]))
    if k1 is None or k2 is None or k1 == k2 or (k1, k2) in seen or k1 not in ref or k2 not in ref: continue
    seen.add((k1, k2))
    r, e = rel(ref[k1], ref[k2]), rel(est[k1], est[k2])
    terr.append(math.hypot(r[0]-e[0], r[1]-e[1]))
    d = (r[2]-e[2] + math.pi) % (2*math.pi) - math.pi
    rerr.append(abs(math.degrees(d)))
terr.sort(); rerr.sort()
n = len(terr)
print("n=%d t_mean=%.4f t_med=%.4f t_max=%.2f r_mean=%.3f >0.2m=%d" % (n, sum(terr)/n, terr[n//2], terr[-1], sum(rerr)/n, sum(1 for t in terr if t > 0.2)))
