"""Run a documentation page's code as a newcomer does: its shell blocks in one shell and its python blocks in one
Python process (like a notebook), each in the order given, in a scratch working folder laid out like a clone
(links to the repository's files, the venv the set-up made, ``../shared`` when present) with a fresh
LEARNEST_HOME, and each block's stdout recorded for the output blocks (docs/_hooks/outputs.py).  The shell and
the Python process share only the folder and LEARNEST_HOME; the language the page shows first runs first.

What is not run literally, and why:

* **Set-up**: a command (one ``&&``-part of a line) that makes the environment: ``python3 -m venv``,
  ``pip install`` (also ``.venv/bin/pip install``), ``docker build``, ``docker run``.  The suite already runs
  inside the environment they make (.ci/run runs the README's set-up literally); the scratch folder's
  ``.venv`` is a link to it, so ``.venv/bin/learnest`` and ``source .venv/bin/activate`` reach the installed
  package.  Docker needs a daemon and a network the suite does not have.
* **The suite itself**: ``.venv/bin/pytest`` would run this test again.  .ci/run runs it literally
  (tests/docs/test_commands.py checks that .ci/run holds the README's command).
* **`learnest serve`** runs until stopped.  It is started in the background with ``--port`` added (the
  default 8000 may be taken on a shared machine), asked ``/health`` until it answers 200 and then ``/`` (the
  pages), and stopped with SIGINT as Ctrl-C stops it; it must exit cleanly.

PATH is this machine's without the venv's ``bin``: a bare ``learnest`` fails as it would for a newcomer who
did not activate the venv.
"""
from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

SETUP = re.compile(r"^\s*(python3? -m venv|(\S*/)?pip3? install|docker (build|run))\b")
SUITE = re.compile(r"^\s*(\S*/)?pytest\b")
SERVE = re.compile(r"^\s*(\S*/)?learnest serve\b")
MARK = "@@learnest-docs-block {}@@"

# Starts the documented `learnest serve` on a free port, waits for /health to answer 200 and / to show the
# pages, then stops it as Ctrl-C does (SIGINT); a server that dies or does not answer fails the block.
SERVE_FUNCTION = r'''
learnest_docs_serve() {
  "$@" --port "$LEARNEST_DOCS_PORT" > "$LEARNEST_DOCS_SERVE_LOG" 2>&1 &
  local pid=$!
  "$LEARNEST_DOCS_PYTHON" - "$LEARNEST_DOCS_PORT" "$pid" <<'PROBE' || { kill -INT "$pid"; wait "$pid"; return 1; }
import os, sys, time, urllib.error, urllib.request
port, pid = sys.argv[1], int(sys.argv[2])
deadline = time.monotonic() + 180
while True:
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=10) as answer:
            if answer.status == 200:
                break
    except (urllib.error.URLError, OSError):
        pass
    os.kill(pid, 0)                      # the server is still running (raises when it is gone)
    if time.monotonic() > deadline:
        sys.exit("learnest serve did not answer /health with 200 within 180 s")
    time.sleep(0.2)
with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30) as page:
    assert page.status == 200 and b"learnest" in page.read(), "/ did not show the pages"
PROBE
  kill -INT "$pid"
  wait "$pid"
}
'''


@dataclass
class PageRun:
    """What running one page printed: per code block (in page order) its stdout, or None when it did not run."""

    page: str
    stdout: list[str | None] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)


def runnable_shell(block: str) -> str:
    """A shell block as the test runs it: set-up and the suite's own command left out, `learnest serve`
    started, probed and stopped (the module's docstring says why); every other line as printed."""
    lines = []
    for line in block.replace("\\\n", " ").splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        kept = []
        for part in re.split(r"\s&&\s", line):
            if SETUP.match(part) or SUITE.match(part):
                continue
            if SERVE.match(part):
                part = "learnest_docs_serve " + re.sub(r"\s+#.*$", "", part).strip()
            kept.append(part.strip())
        if kept:
            lines.append(" && ".join(kept))
    return "\n".join(lines) + "\n"


def scratch_folder(root: Path, tmp: Path) -> Path:
    """A working folder laid out like a clone of ``root`` with its set-up done: ``.venv`` links to this
    interpreter's venv; ``../shared`` links to the one beside ``root`` when there is one."""
    work = tmp / "learnest"
    work.mkdir()
    for entry in root.iterdir():   # a notebook in a clone's root imports its learnest/ folder first: so here
        if not entry.name.startswith(".") and entry.name not in ("build", "site") and "egg-info" not in entry.name:
            (work / entry.name).symlink_to(entry)
    (work / ".venv").symlink_to(sys.prefix, target_is_directory=True)
    shared = root.parent / "shared"
    if shared.is_dir():
        (tmp / "shared").symlink_to(shared, target_is_directory=True)
    return work


def newcomer_env(tmp: Path, port: int) -> dict[str, str]:
    """The environment a newcomer's shell has: no venv on PATH, a fresh LEARNEST_HOME, no network."""
    venv_bin = str(Path(sys.executable).parent)
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "PYTHONPATH")}
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if p and p != venv_bin)
    (tmp / "home").mkdir()
    (tmp / "tmp").mkdir()
    env.update(LEARNEST_HOME=str(tmp / "home"), TMPDIR=str(tmp / "tmp"), MPLBACKEND="Agg",
               HTTP_PROXY="http://127.0.0.1:9", HTTPS_PROXY="http://127.0.0.1:9", NO_PROXY="127.0.0.1,localhost",
               LEARNEST_DOCS_PORT=str(port), LEARNEST_DOCS_PYTHON=sys.executable,
               LEARNEST_DOCS_SERVE_LOG=str(tmp / "serve.log"))
    return env


def _split(stdout: str, count: int) -> list[str | None]:
    parts: list[str | None] = [None] * count
    pieces = re.split(r"^@@learnest-docs-block (\d+)@@\n", stdout, flags=re.M)
    for index, text in zip(pieces[1::2], pieces[2::2]):
        parts[int(index)] = text
    return parts


def run_page(page: Path, name: str, pairs: list, work: Path, env: dict[str, str], timeout: float = 900) -> PageRun:
    """Run the page's ``pairs`` (docs/_hooks/outputs.code_blocks) in ``work``: python blocks in one process,
    shell blocks in one shell (``set -euo pipefail``), each block's stdout kept."""
    result = PageRun(name, [None] * len(pairs))
    for language in dict.fromkeys(code.info for code, _ in pairs):   # the language the page starts with first
        chosen = [(k, code.text) for k, (code, _) in enumerate(pairs) if code.info == language]
        if not chosen:
            continue
        if language == "python":
            script = "".join(f"print({MARK.format(k)!r}, flush=True)\n{text}" for k, text in chosen)
            command = [sys.executable, "-c", script]
        else:
            script = SERVE_FUNCTION + "".join(f"echo '{MARK.format(k)}'\n{runnable_shell(text)}" for k, text in chosen)
            command = ["bash", "-euo", "pipefail", "-c", script]
        run = subprocess.run(command, cwd=work, env=env, capture_output=True, text=True, timeout=timeout)
        for k, text in enumerate(_split(run.stdout, len(pairs))):
            if text is not None:
                result.stdout[k] = text
        if run.returncode != 0:
            serve_log = Path(env["LEARNEST_DOCS_SERVE_LOG"])
            log = serve_log.read_text(errors="replace")[-2000:] if serve_log.is_file() else ""
            result.failures.append(f"{name}: its {language} blocks exited {run.returncode}\n--- stdout\n"
                                   f"{run.stdout[-3000:]}\n--- stderr\n{run.stderr[-3000:]}\n--- serve log\n{log}")
    return result


def write_record(folder: Path, record_name: str, run: PageRun) -> None:
    """Keep the run for the docs build (docs/_hooks/outputs.py reads ``LEARNEST_DOCS_RUN``)."""
    (folder / record_name).write_text(json.dumps({"page": run.page, "stdout": run.stdout}), encoding="utf-8")


def outputs_hook(root: Path):
    """docs/_hooks/outputs.py, the MkDocs hook that holds the output blocks' rules (not a package module)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("learnest_docs_outputs", root / "docs" / "_hooks" / "outputs.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module   # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


def documented_pages(root: Path) -> list[Path]:
    """The README, then every page of docs/ (sorted), that has a bash or python block."""
    pages = [root / "README.md", *sorted(p for p in (root / "docs").rglob("*.md") if "_hooks" not in p.parts)]
    return [p for p in pages if re.search(r"^```(bash|python)\s*$", p.read_text(encoding="utf-8"), re.M)]
