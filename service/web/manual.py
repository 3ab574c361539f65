"""The user manual at /manual, beside the API's own /docs: the MkDocs site of docs/, built on this machine.

Built on this machine, not at install: the wheel then carries only the manual's sources (the package
`learnest.manual`, the repository's docs/ folder), and installing learnest needs no MkDocs. `learnest serve`
starts the build as soon as the service is up (`build_in_background`); a visitor who comes while it runs gets
a page that says so and reloads itself, at once. Without a build under way, the first visitor waits for it
(one at a time, in a separate process). The site is kept under
``LEARNEST_HOME/manual/<key>``, where the key hashes the sources and the installed version, so an upgrade or an
edited page is rebuilt and nothing stale is served. Without the ``docs`` extra the page says how to get it
(503), instead of failing. The site is plain files that load nothing from the internet (mkdocs.yml: no web
fonts, no CDN), so /manual works offline like /docs.
"""
from __future__ import annotations

import functools
import hashlib
import importlib.util
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from html import escape
from pathlib import Path

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse, Response

router = APIRouter(include_in_schema=False)
log = logging.getLogger("learnest.manual")

BUILD_TIMEOUT_S = 300
# Material for MkDocs prints an end-of-life banner on every `mkdocs` run and names its own switch to turn it
# off. Every build of these docs sets it: this one, the suite's (tests/docs), and the command the getting-started
# page prints. The theme stays on MkDocs 1 (its own requirement, mkdocs<2, mirrored in the docs extra).
MKDOCS_ENV = {"NO_MKDOCS_2_WARNING": "1"}
BACKGROUND_NICENESS = 10   # `nice -n` of a build nobody waits for (`build_in_background`)
_build_lock = threading.Lock()


def manual_sources() -> Path | None:
    """The folder of the manual's sources (docs/, installed as the data package `learnest.manual`)."""
    spec = importlib.util.find_spec("learnest.manual")
    if spec is None or not spec.submodule_search_locations:
        return None
    folder = Path(list(spec.submodule_search_locations)[0])
    return folder if (folder / "mkdocs.yml").is_file() and (folder / "index.md").is_file() else None


@functools.lru_cache(maxsize=4)   # once per process: the installed sources do not change while it serves
def _key(sources: Path) -> str:
    """Hash of every source file and the installed version: a change of either is a new build."""
    from importlib.metadata import PackageNotFoundError, version

    digest = hashlib.sha256()
    try:
        digest.update(version("learnest").encode())
    except PackageNotFoundError:  # pragma: no cover - a checkout that was never installed
        pass
    for path in sorted(p for p in sources.rglob("*") if p.is_file() and "__pycache__" not in p.parts):
        digest.update(str(path.relative_to(sources)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


class ManualUnavailable(Exception):
    """The manual cannot be built here; the message says why and what to do."""


def built_manual(home: Path, niceness: int = 0) -> Path:
    """The folder of the built site for these sources, building it first if needed (its MkDocs process at
    ``niceness``, where the ``nice`` command exists: a background build yields the cores to the service).

    Raises
    ------
    ManualUnavailable
        When the sources or MkDocs are missing, or the build fails (with its last lines of output).
    """
    sources = manual_sources()
    if sources is None:
        raise ManualUnavailable("this installation carries no manual sources (the learnest.manual package).")
    if importlib.util.find_spec("mkdocs") is None:
        raise ManualUnavailable("the manual is built with MkDocs, which is not installed here. Install the docs "
                                "extra, pip install \"learnest[docs]\", and reload this page.")
    site = (home / "manual" / _key(sources)).resolve()
    if (site / "index.html").is_file():
        return site
    with _build_lock:
        if (site / "index.html").is_file():  # built while this request waited
            return site
        site.parent.mkdir(parents=True, exist_ok=True)
        work = Path(tempfile.mkdtemp(prefix="build-", dir=site.parent))
        try:
            # the packaged config names its docs folder and hook relative to the repository; point them here
            config = work / "mkdocs.yml"
            config.write_text(f"INHERIT: {sources / 'mkdocs.yml'}\ndocs_dir: {sources}\n"
                              f"hooks:\n  - {sources / '_hooks' / 'reference.py'}\n", encoding="utf-8")
            nice = ["nice", "-n", str(niceness)] if niceness and shutil.which("nice") else []
            run = subprocess.run([*nice, sys.executable, "-m", "mkdocs", "build", "--quiet", "--config-file",
                                  str(config), "--site-dir", str(work / "site")], cwd=work, capture_output=True,
                                 text=True, timeout=BUILD_TIMEOUT_S, env={**os.environ, **MKDOCS_ENV})
            if run.returncode != 0 or not (work / "site" / "index.html").is_file():
                tail = "\n".join((run.stdout + run.stderr).strip().splitlines()[-15:])
                raise ManualUnavailable(f"building the manual failed:\n{tail}")
            if site.exists():  # a build a crash interrupted before its index was in place
                shutil.rmtree(site)
            os.replace(work / "site", site)  # atomic: a reader sees the whole site or none
        except subprocess.TimeoutExpired as error:
            raise ManualUnavailable(f"building the manual took more than {BUILD_TIMEOUT_S} s.") from error
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return site


def build_in_background(home: Path) -> threading.Thread | None:
    """Start building the manual for ``home`` in a thread (None when it is built already or cannot be: the
    first request then says why), at a low CPU priority: requests, jobs and a benchmark beside it come first.
    A build that fails is logged; the next visitor's request then builds it, or shows why not."""
    sources = manual_sources()
    if sources is None or importlib.util.find_spec("mkdocs") is None:
        return None
    if (home / "manual" / _key(sources) / "index.html").is_file():
        return None

    def build() -> None:
        try:
            built_manual(home, niceness=BACKGROUND_NICENESS)
        except (ManualUnavailable, OSError) as error:
            log.warning("the manual was not built: %s", error)

    thread = threading.Thread(target=build, name="learnest-manual-build", daemon=True)
    thread.start()
    return thread


def _building() -> HTMLResponse:
    """The answer while a build runs: at once, and the page reloads itself until the manual is there."""
    body = ("<!doctype html><title>learnest manual</title><meta http-equiv='refresh' content='2'>"
            "<h1>The manual is being built</h1><p>It is built once on this machine, in about half a minute; "
            "this page reloads itself. The API reference is at <a href=\"/docs\">/docs</a> meanwhile.</p>")
    return HTMLResponse(body, status_code=503, headers={"Retry-After": "2", "Cache-Control": "no-store"})


def _unavailable(reason: str) -> HTMLResponse:
    body = (f"<!doctype html><title>learnest manual</title><h1>The manual is not available</h1>"
            f"<pre>{escape(reason)}</pre><p>The API reference is at <a href=\"/docs\">/docs</a>; the manual's sources "
            f"are the Markdown files of the repository's docs/ folder.</p>")
    return HTMLResponse(body, status_code=503)


@router.get("/manual")
def manual_root() -> Response:
    return RedirectResponse("/manual/index.html")


@router.get("/manual/{path:path}")
def manual_page(path: str, request: Request) -> Response:
    """A file of the built manual (built on the first request; while a build runs, a page that says so)."""
    if _build_lock.locked():   # a build under way (the server's own, or another visitor's): no queueing behind it
        return _building()
    try:
        site = built_manual(Path(request.app.state.services.settings.home))
    except ManualUnavailable as error:
        return _unavailable(str(error))
    target = (site / (path or "index.html")).resolve()
    if target.is_dir():
        target = target / "index.html"
    if not target.is_relative_to(site) or not target.is_file():
        return HTMLResponse("<!doctype html><title>Not found</title><h1>No such page in the manual</h1>"
                            "<p><a href=\"/manual/index.html\">The manual's first page</a></p>", status_code=404)
    return FileResponse(target)
