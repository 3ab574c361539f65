"""MkDocs hook: a printed output in the docs must be what its command prints.

An output block is a fenced block opened with ```` ```text title="Output" ```` right after a `bash` or
`python` block (blank lines between are allowed): it shows what that block prints on stdout.  The test suite
runs every such page (tests/docs/test_commands.py) and records each block's stdout in a folder, one JSON file
per page; a build with ``LEARNEST_DOCS_RUN`` naming that folder compares every output block with the run and
fails, naming the page, the block and the first line that differs.  Without ``LEARNEST_DOCS_RUN`` (a plain
`mkdocs build`, `learnest serve`'s manual) nothing is run or compared: building the site never trains a model.

What may differ between the page and the run, and nothing else:

* runs of spaces inside a line (column alignment: a wider number shifts a table's columns) and trailing spaces;
* ``<time>`` in the page stands for a duration or a clock time (digits, ``.`` and ``:``): it varies run to run;
* ``<path>`` in the page stands for a path without spaces: temporary folders differ on every run;
* a line holding only ``...`` stands for any number of lines the page leaves out for length.

Every number other than a time, every word and every line shown must match: a changed number fails.
"""
from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

RUN_ENV = "LEARNEST_DOCS_RUN"
OUTPUT_INFO = 'text title="Output"'
LANGUAGES = ("bash", "python")
_FENCE = re.compile(r"^```(.*)$")
PLACEHOLDERS = {"<time>": r"[0-9][0-9.:]*", "<path>": r"\S+"}


@dataclass(frozen=True)
class Block:
    """A fenced block of a page: its language (the fence's info string), text, and the lines of its opening
    and closing fences (1-based)."""

    info: str
    text: str
    line: int
    end: int

    @property
    def is_output(self) -> bool:
        return self.info == OUTPUT_INFO


def blocks(markdown: str) -> list[Block]:
    """Every fenced block of a Markdown page, in order (fences at the start of a line)."""
    found: list[Block] = []
    info: str | None = None
    start = 0
    body: list[str] = []
    for number, line in enumerate(markdown.splitlines(), start=1):
        fence = _FENCE.match(line)
        if info is None and fence:
            info, start, body = fence.group(1).strip(), number, []
        elif info is not None and line.rstrip() == "```":
            found.append(Block(info, "\n".join(body) + "\n", start, number))
            info = None
        elif info is not None:
            body.append(line)
    return found


def code_blocks(markdown: str) -> list[tuple[Block, Block | None]]:
    """The page's `bash` and `python` blocks in order, each with the output block that follows it (or None).

    Raises
    ------
    ValueError
        An output block that follows no bash or python block: it could not be checked.
    """
    pairs: list[tuple[Block, Block | None]] = []
    lines = markdown.splitlines()
    previous: Block | None = None
    for block in blocks(markdown):
        if block.is_output:
            between = lines[previous.end:block.line - 1] if previous else []
            if previous is None or previous.info not in LANGUAGES or any(s.strip() for s in between) or \
                    pairs[-1][1] is not None:
                raise ValueError(f"line {block.line}: an output block must follow a bash or python block")
            pairs[-1] = (pairs[-1][0], block)
        elif block.info in LANGUAGES:
            pairs.append((block, None))
        previous = block
    return pairs


def _line_pattern(documented: str) -> re.Pattern[str]:
    parts = re.split(r"(<time>|<path>| +)", documented.rstrip())
    regex = "".join(PLACEHOLDERS.get(p) or (" +" if p.strip() == "" and p else re.escape(p)) for p in parts)
    return re.compile(regex + r" *")


def differences(documented: str, printed: str) -> list[str]:
    """How ``printed`` (a run's stdout) differs from ``documented`` (an output block), by the rules above:
    [] when they agree, else one message naming the first line that does not."""
    want = documented.splitlines()
    got = [line.rstrip() for line in printed.strip("\n").splitlines()]
    return _match(want, got, 0, 0)


def _match(want: list[str], got: list[str], i: int, j: int) -> list[str]:
    while i < len(want):
        if want[i].strip() == "...":
            if i + 1 == len(want):
                return []
            for k in range(j, len(got) + 1):   # the fewest lines left out that let the rest agree
                if not _match(want, got, i + 1, k):
                    return []
            return [f"no printed line after line {j} matches the page's {want[i + 1]!r}"]
        if j >= len(got):
            return [f"the page shows {want[i]!r}, the run printed nothing more"]
        if not _line_pattern(want[i]).fullmatch(got[j]):
            return [f"the page shows {want[i]!r}, the run printed {got[j]!r}"]
        i, j = i + 1, j + 1
    return [] if j == len(got) else [f"the run printed more: {got[j]!r} (end the page's output with '...')"]


def record_name(src_uri: str) -> str:
    """The file in the run folder that records the page ``src_uri`` ("tutorials/train.md")."""
    return src_uri.replace("/", "__") + ".json"


def check_page(markdown: str, record: dict[str, Any] | None, name: str) -> list[str]:
    """Every output block of a page against its recorded run (``{"stdout": [per code block]}``)."""
    problems = []
    pairs = code_blocks(markdown)
    outputs = [(k, code, out) for k, (code, out) in enumerate(pairs) if out is not None]
    if outputs and record is None:
        return [f"{name}: no run of this page is recorded"]
    for k, code, out in outputs:
        printed = record["stdout"][k] if record and k < len(record["stdout"]) else None
        if printed is None:
            problems.append(f"{name}, line {out.line}: the {code.info} block above it did not run to here")
            continue
        problems += [f"{name}, line {out.line}: {d}" for d in differences(out.text, printed)]
    return problems


# -- MkDocs events -------------------------------------------------------------------------------------------
_problems: list[str] = []


def on_pre_build(config: Any) -> None:
    """Start each build with no problems found."""
    _problems.clear()


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Check the page's output blocks against the recorded run (only when ``LEARNEST_DOCS_RUN`` is set)."""
    folder = os.environ.get(RUN_ENV)
    src = page.file.src_uri
    try:
        code_blocks(markdown)
    except ValueError as err:
        _problems.append(f"{src}, {err}")
        return markdown
    if folder:
        path = Path(folder) / record_name(src)
        record = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else None
        _problems.extend(check_page(markdown, record, src))
    return markdown


def on_post_build(config: Any) -> None:
    """Fail the build when a documented output differs from its run."""
    if _problems:
        from mkdocs.exceptions import PluginError

        raise PluginError("documented output differs from a run:\n  " + "\n  ".join(_problems))
