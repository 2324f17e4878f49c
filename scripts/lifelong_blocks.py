#!/usr/bin/env python3
"""A long `evermap-demo lifelong` run in blocks of sessions, and its charts.

    scripts/lifelong_blocks.py REPORT.json [--charts DIR]

Reads the run's `report.json` (rewritten after every session, so a run still going can be read) and
prints, per block of sessions (1-15, 16-25, 26-50, 51-75, 76-100, as far as the run got), the graph's
size, PGR CPU per session (p95 and max), resident memory, placements and the paper's scores, then the
figures issue 34's targets judge: block means of the graph from sessions 15-25 to the last block, the
PGR CPU trend, RSS after session 15, and CRI / AMS of the last 25 sessions against the first 25. PGR's CPU
time depends on what else the machine runs (two runs of the same sessions differ by up to 3x); its
Levenberg-Marquardt steps do not, so they are listed beside it.
With --charts, writes three SVG line charts per session (graph size, PGR CPU and RSS, scores) to DIR.
Standard library only.
"""
import json
import math
import sys

BLOCKS = [(1, 15), (16, 25), (26, 50), (51, 75), (76, 100)]


def p95(values):
    values = sorted(values)
    return values[min(len(values) - 1, math.ceil(0.95 * len(values)) - 1)] if values else float("nan")


def mean(values):
    values = list(values)
    return sum(values) / len(values) if values else float("nan")


def block_rows(sessions):
    rows = []
    for first, last in BLOCKS:
        block = [s for s in sessions if first <= s["session"] <= last]
        if not block:
            break
        got = block[-1]["session"]
        right = sum(1 for s in block if s.get("initialized"))
        rows.append({
            "sessions": f"{first}–{got}",
            "nodes": f"{min(s['nodes'] for s in block)}–{max(s['nodes'] for s in block)}",
            "submaps": f"{min(s['submaps'] for s in block)}–{max(s['submaps'] for s in block)}",
            "constraints": f"{min(s['constraints'] for s in block)}–{max(s['constraints'] for s in block)}",
            "pgr": f"{p95([s['pgr_cpu_ms'] for s in block if s.get('pgr_cpu_ms') is not None]):.0f} / "
                   f"{max((s['pgr_cpu_ms'] or 0) for s in block):.0f}",
            "lm": f"{mean(s['pgr_iterations'] for s in block):.1f}",
            # Reports before session 51 lack the factor's size.
            "factor": (f"{mean(s['pgr_factor_nonzeros'] for s in block) / 1e6:.2f}"
                       if all("pgr_factor_nonzeros" in s for s in block) else "–"),
            "rss": f"{mean(s['rss_mb'] for s in block if s.get('rss_mb')):.0f} / "
                   f"{max((s.get('peak_rss_mb') or 0) for s in block):.0f}",
            "cri": f"{right}/{len(block)}",
            "ams": f"{mean(s.get('ams') or 0.0 for s in block):.3f}",
            "mrcl": f"{mean(s['mrcl'] for s in block):.3f}",
        })
    return rows


def growth(sessions, key, base=(15, 25)):
    """Mean of `key` over the last block against sessions base[0]..base[1], in %."""
    last_first = max(first for first, _ in BLOCKS if any(s["session"] >= first for s in sessions))
    before = mean(s[key] for s in sessions if base[0] <= s["session"] <= base[1])
    after = mean(s[key] for s in sessions if s["session"] >= last_first)
    return 100.0 * (after / before - 1.0), last_first


def svg_chart(path, title, y_label, series, y_min=0.0):
    """A line chart of `series` [(name, colour, [(x, y)])] as an SVG file."""
    w, h, left, right, top, bottom = 720, 420, 70, 20, 40, 50
    xs = [x for _, _, pts in series for x, _ in pts]
    ys = [y for _, _, pts in series for _, y in pts]
    if not xs:
        return
    x0, x1 = min(xs), max(xs)
    y0, y1 = (y_min if y_min is not None else min(ys)), max(ys)
    if x1 == x0:
        x1 = x0 + 1
    if y1 == y0:
        y1 = y0 + 1
    sx = lambda x: left + (x - x0) / (x1 - x0) * (w - left - right)
    sy = lambda y: h - bottom - (y - y0) / (y1 - y0) * (h - top - bottom)
    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" '
           f'font-size="12"><rect width="100%" height="100%" fill="white"/>',
           f'<text x="{w / 2}" y="20" text-anchor="middle" font-size="14">{title}</text>',
           f'<line x1="{left}" y1="{h - bottom}" x2="{w - right}" y2="{h - bottom}" stroke="black"/>',
           f'<line x1="{left}" y1="{top}" x2="{left}" y2="{h - bottom}" stroke="black"/>',
           f'<text x="{w / 2}" y="{h - 12}" text-anchor="middle">session</text>',
           f'<text x="16" y="{h / 2}" text-anchor="middle" transform="rotate(-90 16 {h / 2})">{y_label}</text>']
    for i in range(5):
        y = y0 + (y1 - y0) * i / 4
        out.append(f'<text x="{left - 6}" y="{sy(y) + 4:.1f}" text-anchor="end">{y:.4g}</text>')
        out.append(f'<line x1="{left}" y1="{sy(y):.1f}" x2="{w - right}" y2="{sy(y):.1f}" stroke="#ddd"/>')
        x = x0 + (x1 - x0) * i / 4
        out.append(f'<text x="{sx(x):.1f}" y="{h - bottom + 16}" text-anchor="middle">{x:.0f}</text>')
    for k, (name, colour, pts) in enumerate(series):
        line = " ".join(f"{sx(x):.1f},{sy(y):.1f}" for x, y in pts)
        out.append(f'<polyline fill="none" stroke="{colour}" stroke-width="1.5" points="{line}"/>')
        out.append(f'<text x="{left + 10 + 150 * k}" y="{top + 4}" fill="{colour}">{name}</text>')
    out.append("</svg>")
    with open(path, "w") as f:
        f.write("\n".join(out) + "\n")


def main():
    args = sys.argv[1:]
    if not args or args[0].startswith("-"):
        sys.exit(__doc__)
    report = json.load(open(args[0]))
    sessions = [s for s in report["sessions"] if s["session"] >= 1]
    print(f"seed {report.get('seed')}, policy {report.get('policy')}, sessions 1–{sessions[-1]['session']}"
          f"{'' if report.get('complete') else ' (run not complete)'}\n")
    print("| sessions | nodes | submaps | constraints | PGR CPU p95 / max (ms) | LM steps (mean) "
          "| Cholesky factor (M values, mean) | RSS mean / peak (MB) | placed right | AMS mean | MRCL mean |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in block_rows(sessions):
        print(f"| {r['sessions']} | {r['nodes']} | {r['submaps']} | {r['constraints']} | {r['pgr']} | "
              f"{r['lm']} | {r['factor']} | {r['rss']} | {r['cri']} | {r['ams']} | {r['mrcl']} |")
    print()
    for key in ("nodes", "submaps", "constraints"):
        g, last_first = growth(sessions, key)
        print(f"{key}: block mean {last_first}–{sessions[-1]['session']} against 15–25: {g:+.1f} %")
    g, last_first = growth([s for s in sessions if s.get("rss_mb")], "rss_mb")
    print(f"rss_mb: block mean {last_first}–{sessions[-1]['session']} against 15–25: {g:+.1f} %")
    # A placement the robot acted on, committed or not: the report's own verdict (`wrong_placement`,
    # `mapping::metrics::placement_verdict`, 0.5 m or 5° by default); a session placed and then dropped on
    # probation counts here too.
    wrong = [s["session"] for s in sessions if s.get("wrong_placement")]
    print(f"wrong placements acted on: {len(wrong)} {wrong}; never placed: "
          f"{[s['session'] for s in sessions if s['session'] > 0 and s.get('placed_after_s') is None]}; "
          f"placed but never committed: "
          f"{[s['session'] for s in sessions if s.get('placed_after_s') is not None and not s.get('placed')]}")
    if "--charts" in args:
        out = args[args.index("--charts") + 1]
        pts = lambda f: [(s["session"], f(s)) for s in sessions if f(s) is not None]
        svg_chart(f"{out}/graph_size.svg", "graph size after each session", "count", [
            ("nodes", "#1e5ac8", pts(lambda s: s["nodes"])),
            ("submaps x100", "#009600", pts(lambda s: 100 * s["submaps"])),
            ("constraints", "#c82828", pts(lambda s: s["constraints"]))])
        svg_chart(f"{out}/pgr_rss.svg", "PGR CPU per session (ms) and resident memory (MB)", "ms / MB", [
            ("PGR CPU ms", "#c82828", pts(lambda s: s.get("pgr_cpu_ms"))),
            ("RSS MB", "#1e5ac8", pts(lambda s: s.get("rss_mb")))])
        svg_chart(f"{out}/scores.svg", "scores per session", "score / rate", [
            ("AMS", "#1e5ac8", pts(lambda s: s.get("ams"))),
            ("MRCL", "#009600", pts(lambda s: s.get("mrcl"))),
            ("MCR", "#c82828", pts(lambda s: s.get("mcr")))])
        print(f"charts in {out}: graph_size.svg, pgr_rss.svg, scores.svg")


if __name__ == "__main__":
    main()
