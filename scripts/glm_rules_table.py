#!/usr/bin/env python3
"""Each GLM acceptance rule as the test it is, over a robustness suite's runs.

Reads `glm_matches` of OUT_DIR/REC/VARIANT/report.json (what `scripts/robustness_suite.sh OUT_DIR` writes:
each variant's matches judged against its recording's clean run, `--reference-trajectory`) and prints, per
group of variants, one row per rule that decides a match on arrival: how many matches it decided, how many
of those the reference calls wrong, and where they ended (in the final graph, retracted, never used) as
right / wrong. A match is right when it places its node within 0.5 m and 3 degrees of where the reference
puts it, relative to the submap's node nearest the match (`mapping::metrics::judge_matches`). The last line
of each group: the share of the final graph's matches that is wrong.

Usage: glm_rules_table.py OUT_DIR [GROUP=VARIANT,VARIANT ...]
  default groups: `mild` (every variant but clean and hard) and `hard`; runs with no reference are skipped.
"""
import json
import sys
from pathlib import Path

# `refused_by_placement` decides only matches of a placed session (never an offline run); reports of
# builds before it lack the rule and count it as none.
RULES = [
    "accepted", "confirmed", "confirmed_beyond_drift", "held_unconfirmed", "held_beyond_drift",
    "refused_by_placement", "outvoted",
]
FATES = ["in_graph", "retracted", "never_used"]


def load(out: Path):
    runs = {}
    for path in sorted(out.glob("*/*/report.json")):
        report = json.loads(path.read_text())
        if not report.get("glm_matches_reference") or "glm_matches" not in report:
            continue
        runs[(path.parent.parent.name, path.parent.name)] = report["glm_matches"]
    return runs


def table(name: str, tables: list) -> None:
    def total(rule: str, fate: str, key: str) -> int:
        return sum(t.get(rule, {}).get(fate, {}).get(key, 0) for t in tables)

    print(f"\n{name} ({len(tables)} runs)\n")
    print("| rule | matches | wrong | in graph: right / wrong | retracted: right / wrong | never used: right / wrong |")
    print("|---|---|---|---|---|---|")
    for rule in RULES:
        matches = sum(total(rule, f, "matches") for f in FATES)
        right = sum(total(rule, f, "right") for f in FATES)
        wrong = sum(total(rule, f, "wrong") for f in FATES)
        share = f"{wrong} ({100 * wrong / (right + wrong):.1f} %)" if right + wrong else "0"
        cells = [f"{total(rule, f, 'right')} / {total(rule, f, 'wrong')}" for f in FATES]
        print(f"| {rule} | {matches} | {share} | " + " | ".join(cells) + " |")
    right = sum(total(r, "in_graph", "right") for r in RULES)
    wrong = sum(total(r, "in_graph", "wrong") for r in RULES)
    if right + wrong:
        print(f"\nfinal graph: {right + wrong} judged matches, {100 * wrong / (right + wrong):.2f} % wrong")


def main() -> int:
    if len(sys.argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    runs = load(Path(sys.argv[1]))
    if not runs:
        print(f"no judged runs under {sys.argv[1]}", file=sys.stderr)
        return 1
    groups = {}
    for arg in sys.argv[2:]:
        name, _, variants = arg.partition("=")
        groups[name] = set(variants.split(","))
    if not groups:
        variants = {v for _, v in runs}
        groups = {"mild": variants - {"clean", "hard"}, "hard": {"hard"} & variants}
    for name, variants in groups.items():
        tables = [t for (_, v), t in sorted(runs.items()) if v in variants]
        if tables:
            table(f"{name}: {', '.join(sorted(variants))}", tables)
    return 0


if __name__ == "__main__":
    sys.exit(main())
