"""MkDocs hook: write the CLI and API reference pages on every build, so they never go stale.

The CLI page is rendered from `learnest`'s own argparse parser (every subcommand, its usage, its arguments
with their help, defaults and choices); the API page lists every name of `learnest.__all__` at the module
that defines it, for mkdocstrings to render from its numpydoc docstring.  Both pages exist only in the
build (nothing is written into docs/), so a renamed option or a moved function shows at once.
"""
from __future__ import annotations

import argparse
import atexit
import importlib
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

CLI_PAGE = "reference/cli.md"
API_PAGE = "reference/api.md"


def on_startup(command: str, dirty: bool) -> None:
    """Let mkdocstrings find the whole `learnest` package (before any plugin reads `sys.path`).

    An installed wheel or a strict editable install has every subpackage under one `learnest/` folder, where
    mkdocstrings (griffe) looks. A default editable install maps `learnest.ingest` to the repository's
    `ingest/` (and so on) with an import hook griffe does not follow: for it, a temporary folder of links
    that looks like the installed package is put first on the search path.
    """
    tree = _linked_package_tree()
    if tree is not None and tree not in sys.path:
        sys.path.insert(0, tree)


def _linked_package_tree() -> str | None:
    import learnest

    if (Path(learnest.__file__).parent / "ingest").is_dir():
        return None  # already one folder
    mapping: dict[str, str] = {}
    for finder in sys.meta_path:  # setuptools' editable finder keeps its package -> folder map in MAPPING
        module = sys.modules.get(getattr(finder, "__module__", ""))
        mapping.update({k: v for k, v in getattr(module, "MAPPING", {}).items() if k.split(".")[0] == "learnest"})
    if "learnest" not in mapping:
        return None
    tree = Path(tempfile.mkdtemp(prefix="learnest-api-"))
    atexit.register(shutil.rmtree, tree, ignore_errors=True)
    top = tree / "learnest"
    top.mkdir()
    for entry in Path(mapping.pop("learnest")).iterdir():
        (top / entry.name).symlink_to(entry)
    for name, folder in sorted(mapping.items()):
        link = tree.joinpath(*name.split("."))
        link.parent.mkdir(parents=True, exist_ok=True)
        if not link.exists():
            link.symlink_to(folder)
    return str(tree)


def on_files(files: Files, config: Any) -> Files:
    """Add the two generated pages to the build's files (mkdocs calls this once per build)."""
    for path, text in ((CLI_PAGE, cli_reference()), (API_PAGE, api_reference())):
        existing = files.get_file_from_path(path)
        if existing is not None:
            files.remove(existing)
        files.append(File.generated(config, path, content=text))
    return files


def _build_parser() -> argparse.ArgumentParser:
    """The `learnest` parser, wherever the CLI keeps its builder (one module or a `cli` package)."""
    for name in ("learnest.service.cli.parser", "learnest.service.cli"):
        try:
            module = importlib.import_module(name)
        except ImportError:
            continue
        if hasattr(module, "build_parser"):
            return module.build_parser()
    raise RuntimeError("cannot find learnest's build_parser (looked in learnest.service.cli[.parser])")


def _escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _argument_row(action: argparse.Action) -> str | None:
    if action.help == argparse.SUPPRESS or isinstance(action, (argparse._HelpAction,
                                                               argparse._SubParsersAction)):
        return None
    name = ", ".join(f"`{s}`" for s in action.option_strings) or f"`{action.metavar or action.dest}`"
    if action.option_strings and action.nargs != 0:
        metavar = action.metavar or action.dest.upper()
        name += f" `{metavar if isinstance(metavar, str) else ' '.join(metavar)}`"
    notes = []
    if action.required and action.option_strings:
        notes.append("required")
    if action.choices is not None and not isinstance(action.choices, range):
        notes.append("one of " + ", ".join(f"`{c}`" for c in action.choices))
    elif isinstance(action.choices, range):
        notes.append(f"{action.choices.start}-{action.choices.stop - 1}")
    if action.default not in (None, False, argparse.SUPPRESS) and action.nargs != 0:
        notes.append(f"default `{action.default}`")
    if action.nargs in ("*", "+"):
        notes.append("one or more" if action.nargs == "+" else "any number")
    return f"| {name} | {_escape(action.help or '')} | {_escape('; '.join(notes))} |"


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, argparse.ArgumentParser]]:
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help for a in action._choices_actions}
            for name, sub in action.choices.items():
                out.append((name, helps.get(name) or "", sub))
    return out


def _render(parser: argparse.ArgumentParser, name: str, summary: str, depth: int, lines: list[str]) -> None:
    lines.append(f"{'#' * depth} `{name}`")
    lines.append("")
    if summary:
        lines.append(summary[0].upper() + summary[1:] + ("" if summary.endswith(".") else "."))
        lines.append("")
    lines.append("```text")
    usage = parser.format_usage().strip().splitlines()  # argparse indents wrapped lines under "usage: "
    lines += [usage[0].removeprefix("usage: "), *(line.removeprefix(" " * len("usage: ")) for line in usage[1:])]
    lines.append("```")
    lines.append("")
    rows = [row for action in parser._actions if (row := _argument_row(action))]
    if rows:
        lines += ["| argument | what it does | values |", "|---|---|---|", *rows, ""]
    for sub_name, sub_summary, sub in _subcommands(parser):
        _render(sub, f"{name} {sub_name}", sub_summary, min(depth + 1, 4), lines)


def cli_reference() -> str:
    """The CLI reference page, in Markdown, from the parser `learnest` runs."""
    parser = _build_parser()
    lines = ["# CLI reference", "",
             "Generated from the `learnest` command's own parser each time this site is built. "
             "`learnest COMMAND --help` prints the same in a terminal; `learnest --version` prints the "
             "installed version.", ""]
    for name, summary, sub in _subcommands(parser):
        _render(sub, f"learnest {name}", summary, 2, lines)
    return "\n".join(lines) + "\n"


def _where(public: str, obj: Any) -> str:
    """The dotted path of the definition of `learnest.<public>` (the module that defines it)."""
    module = getattr(obj, "__module__", None)
    if module is None:
        return f"learnest.{public}"
    # the definition's own name: a public alias (`thrust_map = thrust_map_report`) has no docstring of its own
    return f"{module}.{getattr(obj, '__qualname__', public)}"


def api_reference() -> str:
    """The API reference page: one mkdocstrings block per public name of `learnest`."""
    import learnest

    groups: dict[str, list[str]] = {"Reading flights": [], "Models and training": [], "Estimators": [],
                                    "Reports": [], "Errors and warnings": []}
    section = {"read_flights": "Reading flights", "Flight": "Reading flights", "IngestError": "Reading flights",
               "KNODE": "Models and training", "HybridModel": "Models and training",
               "make_system": "Models and training", "ukf": "Estimators", "mhe": "Estimators",
               "FilterResult": "Estimators", "MHEResult": "Estimators", "evaluate": "Reports",
               "diagnose": "Reports", "thrust_map": "Reports"}
    for public in learnest.__all__:
        if public.startswith("_"):
            continue
        groups[section.get(public, "Errors and warnings")].append(public)
    lines = ["# API reference", "",
             "Everything `import learnest as le` offers (`learnest.__all__`), generated from the numpydoc "
             "docstrings each time this site is built. Names are imported on first use, so `import learnest` "
             f"stays fast. This build documents learnest {learnest.__version__}.", ""]
    for title, names in groups.items():
        if not names:
            continue
        lines += [f"## {title}", ""]
        for public in names:
            lines += [f"### `le.{public}`", "", f"::: {_where(public, getattr(learnest, public))}",
                      "    options:", "      show_root_heading: false", "      show_root_toc_entry: false", ""]
    return "\n".join(lines) + "\n"
