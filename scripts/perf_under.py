#!/usr/bin/env python3
"""Where the CPU goes under one function: reads `perf script -F ip,sym` (a `perf record --call-graph dwarf`
profile) on standard input and prints, for the samples whose stack holds FUNCTION, the share of each call
chain below it (to DEPTH frames) and of each leaf.

    perf record -o perf.data -F 49 --call-graph dwarf,16384 target/release/evermap-demo lifelong --sessions 12 ...
    perf script -i perf.data --comm lifelong-map -F ip,sym | scripts/perf_under.py finish_session [DEPTH]

Frames inlined by the compiler count as frames (their names end in "(inlined)").
"""
import collections
import sys


def main() -> None:
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    function = sys.argv[1]
    depth = int(sys.argv[2]) if len(sys.argv) > 2 else 3
    chains: collections.Counter = collections.Counter()
    leaves: collections.Counter = collections.Counter()
    total = 0

    def sample(frames: list) -> None:
        nonlocal total
        under = next((i for i, f in enumerate(frames) if function in f), None)
        if under is None:
            return
        total += 1
        leaves[frames[0][:120]] += 1
        path = [f[:100] for f in reversed(frames[:under])]
        for d in range(1, min(depth, len(path)) + 1):
            chains[" > ".join(path[:d])] += 1

    frames: list = []
    for line in sys.stdin:
        if not line.strip():
            sample(frames)
            frames = []
        elif line[0] in " \t":
            parts = line.strip().split(" ", 1)
            frames.append(parts[-1])
        else:
            frames = []
    sample(frames)
    if total == 0:
        sys.exit(f"no sample under {function}")
    print(f"{total} samples under {function}")
    print("call chains below it:")
    for chain, n in sorted(chains.items()):
        if n >= 0.01 * total:
            print(f"  {100 * n / total:5.1f} %  {chain}")
    print("leaves:")
    for leaf, n in leaves.most_common(15):
        print(f"  {100 * n / total:5.1f} %  {leaf}")


if __name__ == "__main__":
    main()
