"""Sizes a reader can hold in mind: no module of the installed package over 500 lines, no function over 80.

A long module is several subjects that want their own names; a long function is steps that want theirs.  The
check reads the installed package's source (what a user gets) with `ast`, so a module moved or added anywhere
in it is measured; a function's length runs from its ``def`` line to its last line (decorators not counted),
nested functions and methods included.
"""
import ast
from pathlib import Path

import learnest

MAX_MODULE_LINES = 500
MAX_FUNCTION_LINES = 80

PACKAGE = Path(learnest.__file__).parent   # not resolved: a strict editable install links its files


def _sources() -> list[tuple[str, str]]:
    """(path relative to the package, text) of every Python module of the installed package."""
    files = sorted(PACKAGE.rglob("*.py"))
    assert len(files) > 100, f"only {len(files)} modules under {PACKAGE}: not the whole installed package"
    return [(f.relative_to(PACKAGE).as_posix(), f.read_text(encoding="utf-8")) for f in files]


def sizes_over_the_limits(sources: list[tuple[str, str]]) -> dict[str, int]:
    """{"path": lines} for modules over MAX_MODULE_LINES and {"path::function": lines} for functions (and
    methods, nested ones too) over MAX_FUNCTION_LINES."""
    over = {}
    for path, text in sources:
        lines = len(text.splitlines())
        if lines > MAX_MODULE_LINES:
            over[path] = lines
        for node in ast.walk(ast.parse(text, filename=path)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                length = node.end_lineno - node.lineno + 1
                if length > MAX_FUNCTION_LINES:
                    over[f"{path}::{node.name}"] = length
    return over


def test_no_module_over_500_lines_and_no_function_over_80():
    over = sizes_over_the_limits(_sources())
    assert over == {}, "over the limits: " + ", ".join(f"{k} ({v} lines)" for k, v in sorted(over.items()))


def test_the_check_measures_what_it_claims():
    """Known answers: a 501-line module and an 81-line function are caught; 500 and 80 lines pass."""
    body = "".join(f"    x{k} = {k}\n" for k in range(79))   # def line + 79 body lines = 80 lines
    ok = "def fits():\n" + body + "\n" * (500 - 80)
    long_function = "def too_long():\n" + body + "    x = 0\n"
    assert sizes_over_the_limits([("ok.py", ok)]) == {}
    assert len(ok.splitlines()) == 500
    assert sizes_over_the_limits([("f.py", long_function)]) == {"f.py::too_long": 81}
    assert sizes_over_the_limits([("m.py", ok + "\n")]) == {"m.py": 501}
