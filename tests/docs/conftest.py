"""The documentation's code, run once per session: tests/docs/test_commands.py checks each page's run, and the
site build (test_docs.py) checks every documented output against it (docs/_hooks/outputs.py)."""
from __future__ import annotations

import socket
import sys
from pathlib import Path

import pytest
from utils.documented import documented_pages, newcomer_env, outputs_hook, run_page, scratch_folder, write_record

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "mkdocs.yml").is_file())


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="session")
def documented_runs(tmp_path_factory) -> tuple[Path, dict]:
    """Every documented page run as a newcomer runs it (tests/utils/documented.py): the folder of records
    for ``LEARNEST_DOCS_RUN`` and {page name: PageRun}."""
    if sys.prefix == sys.base_prefix:
        pytest.skip("the documented commands use the set-up's .venv: run the suite from a virtual environment")
    hook = outputs_hook(ROOT)
    records = tmp_path_factory.mktemp("docs-run")
    runs = {}
    for page in documented_pages(ROOT):
        name = page.relative_to(ROOT).as_posix()
        tmp = tmp_path_factory.mktemp(page.stem)
        work = scratch_folder(ROOT, tmp)
        run = run_page(page, name, hook.code_blocks(page.read_text(encoding="utf-8")), work,
                       newcomer_env(tmp, _free_port()))
        write_record(records, hook.record_name(page.relative_to(ROOT / "docs").as_posix()
                                               if name.startswith("docs/") else name), run)
        runs[name] = run
    return records, runs
