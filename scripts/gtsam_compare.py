#!/usr/bin/env python3
"""Compare `evermap-server optimize` with GTSAM's Levenberg-Marquardt on 2D pose-graph files.

For each file, runs our release binary and GTSAM 4.3 (`pip install gtsam`) from the same initial values,
scores both results with the same g2o-convention chi2 (e = [translation of Z^-1 Xi^-1 Xj, wrap(thj - thi - thz)],
chi2 = sum e^T Omega e), and prints a table.

GTSAM gets: the file converted to g2o if it is TORO; initial values for nodes without VERTEX lines from the
odometry chain (j = i + 1 edges, forwards then backwards, then BFS over any edge), as our reader does; a
tight prior on the smallest node id (our gauge). GTSAM minimises its own error (Pose2 Logmap of the edge
residual), so its result is re-scored here in the g2o convention. Times are wall-clock of the optimization
only (not parsing), best of --repeat runs.

Usage: scripts/gtsam_compare.py [FILES...] [--binary target/release/evermap-server] [--repeat 3]
Build first: cargo build --release --workspace
"""

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections import deque
from pathlib import Path

BEST_KNOWN = {
    "ring.g2o": 11.1631,
    "CSAIL.g2o": 40.5551,
    "intel_sesync1728.g2o": 45.0047,
    "M3500.g2o": 137.9130,
    "city10000.g2o": 511.9852,
    "input_INTEL_g2o.g2o": 215.83,
    "M3500a_toro.graph": 7591.4,
}
DEFAULT_FILES = ["ring.g2o", "CSAIL.g2o", "intel_sesync1728.g2o", "M3500.g2o", "city10000.g2o",
                 "input_INTEL_g2o.g2o", "M3500a_toro.graph"]


def find_datasets(root: Path) -> Path:
    for d in [root, *root.parents]:
        candidate = d / "shared" / "datasets" / "posegraphs"
        if candidate.is_dir():
            return candidate
    return root / ".." / "shared" / "datasets" / "posegraphs"


def compose(a, b):
    x, y, t = a
    c, s = math.cos(t), math.sin(t)
    return (x + c * b[0] - s * b[1], y + s * b[0] + c * b[1], wrap(t + b[2]))


def inverse(a):
    x, y, t = a
    c, s = math.cos(t), math.sin(t)
    return (-(c * x + s * y), s * x - c * y, wrap(-t))


def wrap(t):
    return math.atan2(math.sin(t), math.cos(t))


def parse(path: Path):
    """Returns (vertices {id: (x, y, th)}, edges [(i, j, (dx, dy, dth), (I11, I12, I13, I22, I23, I33))])."""
    vertices, edges = {}, []
    with open(path) as f:
        for line_no, line in enumerate(f, 1):
            tok = line.split()
            if not tok or tok[0].startswith("#"):
                continue
            tag = tok[0]
            if tag in ("VERTEX_SE2", "VERTEX2"):
                vertices[int(tok[1])] = tuple(float(v) for v in tok[2:5])
            elif tag in ("EDGE_SE2", "EDGE2"):
                i, j = int(tok[1]), int(tok[2])
                z = tuple(float(v) for v in tok[3:6])
                v = [float(x) for x in tok[6:12]]
                if tag == "EDGE2":  # I11 I12 I22 I33 I13 I23
                    info = (v[0], v[1], v[4], v[2], v[5], v[3])
                else:  # I11 I12 I13 I22 I23 I33
                    info = tuple(v)
                edges.append((i, j, z, info))
            elif tag == "FIX":
                pass
            else:
                sys.exit(f"{path}:{line_no}: unknown tag {tag!r}")
    return vertices, edges


def initialize(vertices, edges):
    poses = dict(vertices)
    needed = sorted({i for e in edges for i in e[:2]} - set(poses))
    if not needed:
        return poses
    odometry = {}
    for i, j, z, _ in edges:
        if j == i + 1:
            odometry.setdefault(i, z)
    adjacency = {}
    for i, j, z, _ in edges:
        adjacency.setdefault(i, []).append((j, z))
        adjacency.setdefault(j, []).append((i, inverse(z)))
    while True:
        for i in sorted(odometry):
            if i in poses and i + 1 not in poses:
                poses[i + 1] = compose(poses[i], odometry[i])
        for i in sorted(odometry, reverse=True):
            if i + 1 in poses and i not in poses:
                poses[i] = compose(poses[i + 1], inverse(odometry[i]))
        queue = deque(sorted(poses))
        while queue:
            i = queue.popleft()
            for j, z in adjacency.get(i, []):
                if j not in poses:
                    poses[j] = compose(poses[i], z)
                    queue.append(j)
        missing = [i for i in needed if i not in poses]
        if not missing:
            return poses
        poses[missing[0]] = (0.0, 0.0, 0.0)


def chi2(poses, edges):
    total = 0.0
    for i, j, z, (i11, i12, i13, i22, i23, i33) in edges:
        d = compose(inverse(z), compose(inverse(poses[i]), poses[j]))
        ex, ey = d[0], d[1]
        et = wrap(poses[j][2] - poses[i][2] - z[2])
        total += (i11 * ex * ex + i22 * ey * ey + i33 * et * et
                  + 2 * (i12 * ex * ey + i13 * ex * et + i23 * ey * et))
    return total


def write_g2o(path, poses, edges):
    with open(path, "w") as f:
        for i in sorted(poses):
            x, y, t = poses[i]
            f.write(f"VERTEX_SE2 {i} {x!r} {y!r} {t!r}\n")
        for i, j, z, info in edges:
            f.write("EDGE_SE2 %d %d %r %r %r %r %r %r %r %r %r\n" % (i, j, *z, *info))


def run_ours(binary, path, repeat, extra_args=()):
    best = None
    for _ in range(repeat):
        out = subprocess.run([binary, "optimize", "--g2o", str(path), *extra_args], capture_output=True, text=True)
        if out.returncode != 0:
            sys.exit(f"{binary} failed on {path}:\n{out.stderr}")
        result = json.loads(out.stdout.strip().splitlines()[-1])
        if best is None or result["time_ms"] < best["time_ms"]:
            best = result
    return best


def run_gtsam(gtsam, path, repeat, max_iterations):
    vertices, edges = parse(path)
    poses = initialize(vertices, edges)
    with tempfile.TemporaryDirectory() as tmp:
        g2o_path = os.path.join(tmp, "graph.g2o")
        write_g2o(g2o_path, poses, edges)
        graph, initial = gtsam.readG2o(g2o_path, False)
    first = min(poses)
    prior_noise = gtsam.noiseModel.Diagonal.Variances(gtsam.Point3(1e-6, 1e-6, 1e-8))
    graph.add(gtsam.PriorFactorPose2(first, initial.atPose2(first), prior_noise))
    best_ms, result, iterations = math.inf, None, 0
    for _ in range(repeat):
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        start = time.perf_counter()
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
        values = optimizer.optimize()
        elapsed = (time.perf_counter() - start) * 1e3
        if elapsed < best_ms:
            best_ms, result, iterations = elapsed, values, optimizer.iterations()
    optimized = {}
    for i in poses:
        p = result.atPose2(i)
        optimized[i] = (p.x(), p.y(), p.theta())
    # GTSAM's error() is half its chi2 (in its own Logmap convention); report the g2o-convention chi2.
    return {"chi2": chi2(optimized, edges), "gtsam_chi2": 2.0 * graph.error(result),
            "time_ms": best_ms, "iterations": iterations, "initial_chi2": chi2(poses, edges)}


def gtsam_version():
    try:
        from importlib.metadata import version
        return version("gtsam")
    except Exception:  # noqa: BLE001 - the version is informative only
        return "?"


def main():
    root = Path(__file__).resolve().parent.parent
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("files", nargs="*", type=Path)
    parser.add_argument("--binary", default=str(root / "target" / "release" / "evermap-server"))
    parser.add_argument("--repeat", type=int, default=3, help="runs per solver; the fastest is reported")
    parser.add_argument("--gtsam-max-iterations", type=int, default=100)
    parser.add_argument("--our-args", nargs="*", default=[],
                        help="extra arguments for `evermap-server optimize`, e.g. --our-args=--no-rotation-init")
    args = parser.parse_args()
    try:
        import gtsam
    except ImportError:
        sys.exit("gtsam is not installed: run `pip install gtsam` (GTSAM 4.3 Python wheels), then retry.")
    if not os.access(args.binary, os.X_OK):
        sys.exit(f"{args.binary} not found: run `cargo build --release --workspace` first.")
    files = args.files or [find_datasets(root) / name for name in DEFAULT_FILES]

    header = (f"{'file':<22} {'nodes':>6} {'edges':>6} {'our chi2':>12} {'GTSAM chi2':>12} {'best known':>11} "
              f"{'our it':>6} {'GT it':>5} {'our ms':>8} {'GTSAM ms':>9} {'ratio':>6}  our termination")
    print(f"ours: {args.binary} optimize {' '.join(args.our_args)}; GTSAM {gtsam_version()} LM, "
          f"default parameters, maxIterations {args.gtsam_max_iterations}; best of {args.repeat} runs")
    print(header)
    print("-" * len(header))
    for path in files:
        ours = run_ours(args.binary, path, args.repeat, args.our_args)
        theirs = run_gtsam(gtsam, path, args.repeat, args.gtsam_max_iterations)
        best = BEST_KNOWN.get(path.name)
        ratio = ours["time_ms"] / theirs["time_ms"] if theirs["time_ms"] > 0 else math.nan
        print(f"{path.name:<22} {ours['nodes']:>6} {ours['edges']:>6} {ours['final_chi2']:>12.4f} "
              f"{theirs['chi2']:>12.4f} {best if best is not None else math.nan:>11.4f} {ours['iterations']:>6} "
              f"{theirs['iterations']:>5} {ours['time_ms']:>8.1f} {theirs['time_ms']:>9.1f} {ratio:>6.2f}  "
              f"{ours['termination']}")
        sys.stdout.flush()
    print("chi2: g2o convention, computed here for GTSAM's result; 'GT it' counts GTSAM's outer iterations, "
          "'our it' every LM step tried. ratio = our ms / GTSAM ms.")


if __name__ == "__main__":
    main()
