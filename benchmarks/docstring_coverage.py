"""Measure docstring coverage of the public API.

Counts public (not ``_``-prefixed) module-level functions and classes, and the public methods of
public classes, in ``ingest``, ``models``, ``estimators``, ``service`` and ``learnest`` (migrations
excluded). Prints ``documented/total`` and then one ``path:line name`` per undocumented item.

Run from the repository root::

    python3 benchmarks/docstring_coverage.py
"""
import ast
from pathlib import Path

PACKAGES = ("ingest", "models", "estimators", "service", "learnest")


def main() -> None:
    """Print the coverage count and the undocumented names."""
    missing, total = [], 0
    for d in PACKAGES:
        for p in sorted(Path(d).rglob("*.py")):
            if "migrations" in p.parts:
                continue
            for node in ast.parse(p.read_text()).body:
                items = [node]
                if isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
                    items += [n for n in node.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
                for n in items:
                    if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) \
                            and not n.name.startswith("_"):
                        total += 1
                        if not ast.get_docstring(n):
                            missing.append(f"{p}:{n.lineno} {n.name}")
    print(f"{total - len(missing)}/{total}")
    print("\n".join(missing))


if __name__ == "__main__":
    main()
