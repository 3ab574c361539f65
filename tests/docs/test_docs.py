"""The documentation site as tests: it builds offline with warnings as errors, its generated references
cover the real parser and the public API, and its printed outputs are those of a run (the pages' code runs in
test_commands.py)."""
import html
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

import learnest

ROOT = next(p for p in Path(__file__).resolve().parents if (p / "mkdocs.yml").is_file())  # the repository
# no network: a build or a tutorial that reaches for the internet fails instead of passing on a lucky day
OFFLINE = {"HTTP_PROXY": "http://127.0.0.1:9", "HTTPS_PROXY": "http://127.0.0.1:9", "NO_PROXY": "127.0.0.1,localhost"}


def _env(**extra: str) -> dict[str, str]:
    from learnest.service.web.manual import MKDOCS_ENV  # the theme's banner off, as in every build of the docs

    env = {**os.environ, **OFFLINE, **MKDOCS_ENV, **extra}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"  # this venv's learnest
    return env


@pytest.fixture(scope="module")
def site(tmp_path_factory, documented_runs) -> Path:
    """One `mkdocs build --strict` of the repository's docs, shared by the checks below.  It checks every
    documented output against the session's run of the pages (docs/_hooks/outputs.py: ``LEARNEST_DOCS_RUN``),
    so a changed number fails the build; it prints no warning, the theme's advisory banner included."""
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install '.[docs]')")
    records, _ = documented_runs
    out = tmp_path_factory.mktemp("site")
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file",
                          str(ROOT / "mkdocs.yml"), "--site-dir", str(out)], cwd=tmp_path_factory.mktemp("cwd"),
                         env=_env(LEARNEST_DOCS_RUN=str(records)), capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "WARNING" not in run.stderr and "Warning" not in run.stderr and "end of life" not in run.stderr, run.stderr
    return out


def _text(page: Path) -> str:
    return html.unescape(re.sub(r"<[^>]+>", " ", page.read_text(encoding="utf-8")))


def test_the_site_builds_strictly_and_offline(site):
    """Every page of the navigation is built; no page loads anything from the internet (no web fonts, no
    CDN scripts), so the manual works where the service does: on a machine without internet access."""
    for page in ["index.html", "getting-started.html", "tutorials/train.html", "concepts/yardsticks.html",
                 "concepts/checks.html", "reference/cli.html", "reference/api.html", "deployment.html",
                 "results/index.html", "results/table1.html", "changelog.html"]:
        assert (site / page).is_file(), page
    remote = []
    for page in site.rglob("*.html"):
        remote += [(page.name, m) for m in re.findall(r'<(?:script|link|img)[^>]+(?:src|href)="(https?://[^"]+)"',
                                                     page.read_text(encoding="utf-8"))]
    assert remote == []


def test_the_cli_reference_is_the_parser(site):
    """Every subcommand and every option of the real parser is on the CLI page (generated at build time)."""
    from learnest.service import cli

    parser = (getattr(cli, "build_parser", None) or __import__("learnest.service.cli.parser",
                                                              fromlist=["build_parser"]).build_parser)()
    text = _text(site / "reference" / "cli.html")
    [sub] = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
    assert len(sub.choices) >= 10 and "learnest --version" in text
    for name, command in sub.choices.items():
        assert f"learnest {name}" in text, name
        for action in command._actions:
            for option in action.option_strings:
                assert option in text, (name, option)


def test_the_api_reference_covers_the_public_api(site):
    """Each name of learnest.__all__ has its section, rendered from its docstring (not an empty heading)."""
    text = _text(site / "reference" / "api.html")
    for name in learnest.__all__:
        if name.startswith("_"):
            continue
        assert f"le.{name}" in text, name
        doc = (getattr(learnest, name).__doc__ or "").strip().splitlines()
        if doc:  # the docstring's first words, compared without markup or spacing
            first = re.sub(r"[^\w.]", "", "".join(doc[0].split()[:4]))
            assert first in re.sub(r"[^\w.]", "", text), (name, first)


# -- /manual: the same site, served by `learnest serve` ---------------------------------------------------------

def test_serve_builds_the_manual_once_and_serves_it_offline(tmp_path):
    """GET /manual builds the packaged sources on first use into LEARNEST_HOME/manual/<key> and serves the
    pages; the next request reuses the build; nothing outside the site is reachable through the route."""
    pytest.importorskip("mkdocs", reason="the docs extra is not installed (pip install '.[docs]')")
    from utils.service import running_app

    with running_app(tmp_path) as client:
        assert "href='/manual/index.html'" in client.get("/").text   # every page's navigation links to it
        first = client.get("/manual", follow_redirects=False)
        assert first.status_code in (302, 307) and first.headers["location"] == "/manual/index.html"
        page = client.get("/manual/index.html")
        assert page.status_code == 200, page.text[:2000]
        assert "Learning-enhanced state estimation" in page.text
        [site] = list((tmp_path / "manual").iterdir())
        built_at = (site / "index.html").stat().st_mtime_ns
        cli = client.get("/manual/reference/cli.html")
        assert cli.status_code == 200 and "learnest evaluate" in cli.text
        assert (site / "index.html").stat().st_mtime_ns == built_at   # not rebuilt
        assert (tmp_path / "learnest.db").is_file()
        assert client.get("/manual/%2e%2e/%2e%2e/learnest.db").status_code == 404   # ../../learnest.db
        assert client.get("/manual/no-such-page.html").status_code == 404


def test_serve_without_mkdocs_says_what_to_install(tmp_path, monkeypatch):
    """With MkDocs not importable the manual answers 503 with the command that installs it, not a 500."""
    from utils.service import running_app

    monkeypatch.setitem(sys.modules, "mkdocs", None)  # `import mkdocs` fails in this process, as when absent
    with running_app(tmp_path) as client:
        page = client.get("/manual/index.html")
    assert page.status_code == 503
    assert "learnest[docs]" in html.unescape(page.text)
    assert not (tmp_path / "manual").exists()
