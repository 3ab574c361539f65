"""Scan every committed result for a claimed parameter at a physical bound or outside it.

A parameter counts as claimed where its effect entry says ``claimed`` (or ``identified``) true; its bounds are the
effect library's (`models.effects.LIBRARY`, `models.crazyflie.BOUNDS`), "at" meaning within
`models.diagnosis.AT_BOUND_FRACTION` of the range; a thrust gain (no library bounds) is checked by its own
``at_bound`` flag.  Run from the repository root:
    .venv/bin/python benchmarks/claimed_within_bounds.py > benchmarks/results/claimed_within_bounds.md
"""
from __future__ import annotations

import json
from pathlib import Path

from learnest.models.diagnosis import AT_BOUND_FRACTION
from learnest.models.effects import LIBRARY

RESULTS = Path(__file__).parent / "results"
PARAMS = {(e.id, p.name): p for e in LIBRARY.values() for p in e.params}   # two effects have a "k"


def _effects(node):
    if isinstance(node, dict):
        for e in node.get("effects") or []:
            if isinstance(e, dict) and ("claimed" in e or "identified" in e):
                yield e
        for value in node.values():
            yield from _effects(value)
    elif isinstance(node, list):
        for value in node:
            yield from _effects(value)


def main() -> None:
    files, claims, problems = 0, 0, []
    for path in sorted(RESULTS.rglob("*.json")):
        try:
            data = json.loads(path.read_text())
        except (ValueError, UnicodeDecodeError):
            continue
        files += 1
        for e in _effects(data):
            flags = e.get("identified", e.get("claimed", {}))
            for name, claimed in flags.items():
                if not claimed:
                    continue
                claims += 1
                value = e["params"][name]
                if e.get("at_bound", {}).get(name):
                    problems.append(f"{path.relative_to(RESULTS)}: {e['id']}.{name} = {value:.4g} flagged at a bound")
                if (e["id"], name) in PARAMS:
                    p = PARAMS[(e["id"], name)]
                    margin = AT_BOUND_FRACTION * (p.upper - p.lower)
                    if not p.lower + margin < value < p.upper - margin:
                        problems.append(f"{path.relative_to(RESULTS)}: {e['id']}.{name} = {value:.4g} outside or at "
                                        f"[{p.lower:g}, {p.upper:g}]")
    print("# Claimed parameters against their physical bounds, every committed result\n")
    print("Command: `.venv/bin/python benchmarks/claimed_within_bounds.py > "
          "benchmarks/results/claimed_within_bounds.md`\n")
    print(f"{files} JSON result files, {claims} claimed parameters, {len(problems)} at or outside a bound.\n")
    for line in problems:
        print(f"- {line}")


if __name__ == "__main__":
    main()
