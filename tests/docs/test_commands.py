"""Every shell and python block of the README and the docs runs as printed, and every output it shows is what
it prints.  How a page is run, and which lines are set-up and why they are left out: tests/utils/documented.py.
The rules an output block is compared by: docs/_hooks/outputs.py."""
from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from utils.documented import documented_pages, newcomer_env, outputs_hook, runnable_shell

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "mkdocs.yml").is_file())
PAGES = documented_pages(ROOT)
HOOK = outputs_hook(ROOT)


def _name(page: Path) -> str:
    return page.relative_to(ROOT).as_posix()


@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES, ids=[_name(p) for p in PAGES])
def test_the_page_runs_as_printed_and_prints_what_it_shows(page, documented_runs):
    """The page's blocks exit 0 in a fresh working folder and LEARNEST_HOME, and each output block matches."""
    records, runs = documented_runs
    run = runs[_name(page)]
    assert not run.failures, "\n".join(run.failures)
    problems = HOOK.check_page(page.read_text(encoding="utf-8"), {"stdout": run.stdout}, _name(page))
    assert problems == [], "\n".join(problems)


def test_every_page_with_commands_is_run_and_the_tutorials_show_outputs():
    names = {_name(p) for p in PAGES}
    assert {"README.md", "docs/getting-started.md", "docs/tutorials/train.md", "docs/tutorials/evaluate.md",
            "docs/tutorials/diagnose.md", "docs/tutorials/service.md"} <= names
    shown = sum(out is not None for p in PAGES for _, out in HOOK.code_blocks(p.read_text(encoding="utf-8")))
    assert shown >= 5


def _readme_shell_blocks() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    return [b.text for b in HOOK.blocks(text) if b.info == "bash"]


def test_set_up_and_the_suite_are_the_only_commands_left_out():
    """The README's first command keeps its demo, the test command keeps nothing (CI runs it), the editable
    install is set-up, and `learnest serve` is started, probed and stopped; every other line is as printed."""
    demo, tests, editable, cli = _readme_shell_blocks()
    assert runnable_shell(demo) == ".venv/bin/learnest demo sample_logs\n"
    assert runnable_shell(tests).strip() == "" and runnable_shell(editable).strip() == ""
    ran = runnable_shell(cli).splitlines()
    printed = [line for line in cli.splitlines() if line.strip() and not line.startswith("#")]
    assert len(ran) == len(printed)
    for line, as_run in zip(printed, ran):
        if " serve" in line:
            assert as_run == "learnest_docs_serve " + line.split("#")[0].strip()
        else:
            assert as_run == line


def test_ci_runs_the_readmes_set_up_and_test_command_literally():
    """The one README command the suite cannot run (itself) is what .ci/run runs, part for part."""
    ci = [re.sub(r"\s+#.*$", "", line).strip() for line in (ROOT / ".ci" / "run").read_text().splitlines()]
    tests = _readme_shell_blocks()[1].strip()
    for part in tests.split(" && "):
        assert part in ci, part


def test_a_bare_learnest_is_not_found_without_the_venv(tmp_path):
    """The pages run without the venv on PATH, as a newcomer's shell: only the printed set-up finds it."""
    env = newcomer_env(tmp_path, 9)
    run = subprocess.run(["bash", "-c", "command -v learnest"], env=env, capture_output=True, text=True)
    assert run.returncode != 0, f"learnest is on the PATH outside the venv: {run.stdout}"


def test_a_changed_number_in_an_output_block_fails_and_only_times_and_paths_may_vary():
    documented = ("registered circle:1: 20 epochs in <time> s, kept epoch 19; registry in <path>\n"
                  "version  status   final loss  train s\n"
                  "      1  ready       0.00717      <time>\n"
                  "...\n"
                  "stored as evaluation 1\n")
    printed = ("registered circle:1: 20 epochs in 12.5 s, kept epoch 19; registry in /tmp/x/home\n"
               "version  status   final loss  train s\n"
               "      1  ready       0.00717     12.5\n"
               "a line left out\nanother\n"
               "stored as evaluation 1\n")
    assert HOOK.differences(documented, printed) == []
    assert HOOK.differences(documented, printed.replace("0.00717", "0.00718")) != []
    assert HOOK.differences(documented, printed.replace("epoch 19", "epoch 18")) != []
    assert HOOK.differences(documented, printed + "one more line\n") != []
    assert HOOK.differences(documented.replace("...\n", ""), printed) != []


def test_an_output_block_must_follow_a_command():
    page = "Text.\n\n```text title=\"Output\"\n42\n```\n"
    with pytest.raises(ValueError, match="must follow a bash or python block"):
        HOOK.code_blocks(page)
    pairs = HOOK.code_blocks("```bash\necho 42\n```\n\n```text title=\"Output\"\n42\n```\n")
    assert [(code.text, out.text) for code, out in pairs] == [("echo 42\n", "42\n")]
