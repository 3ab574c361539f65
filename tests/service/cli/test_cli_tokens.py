"""`learnest tokens create|list|revoke` and `learnest audit` on the registry the server uses, and `learnest serve`
refusing an address other than loopback while the server has no token, and what it hands uvicorn."""
from __future__ import annotations

import json
from argparse import Namespace

import pytest

from learnest.service.cli import main


@pytest.fixture
def home(tmp_path, monkeypatch):
    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    return tmp_path / "home"


def test_tokens_are_made_listed_revoked_and_audited(home, capsys):
    assert main(["tokens", "list"]) == 2
    assert "no token has been made under" in capsys.readouterr().err
    assert main(["tokens", "create", "ada", "--scope", "admin"]) == 0
    out = capsys.readouterr()
    token = out.out.strip()
    assert token.startswith("lnst_") and len(token) > 40 and "printed this once" in out.err
    assert main(["tokens", "create", "rui", "--scope", "read", "--json"]) == 0
    rui = json.loads(capsys.readouterr().out)
    assert rui["scope"] == "read" and rui["token"].startswith("lnst_") and rui["created_by"].startswith("local:")
    assert main(["tokens", "create", "rui", "--scope", "read"]) == 2
    assert "a token named 'rui' exists" in capsys.readouterr().err
    assert main(["tokens", "create", "eve", "--scope", "owner"]) == 2          # argparse names the choices
    assert "invalid choice: 'owner'" in capsys.readouterr().err
    assert main(["tokens", "list"]) == 0
    listed = capsys.readouterr().out
    assert "2 token(s), 2 not revoked" in listed and token not in listed and rui["token"] not in listed
    assert main(["tokens", "revoke", "rui"]) == 0
    assert "revoked token 2 (rui, read)" in capsys.readouterr().out
    assert main(["tokens", "revoke", "2"]) == 2
    assert "was revoked at" in capsys.readouterr().err
    assert main(["tokens", "list", "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [(r["name"], r["revoked_at"] is not None) for r in rows] == [("ada", False), ("rui", True)]
    assert main(["audit", "--json"]) == 0
    log = json.loads(capsys.readouterr().out)
    assert log["total"] == 3 and [e["action"] for e in log["items"]] == ["token.revoke", "token.create",
                                                                         "token.create"]
    assert main(["audit"]) == 0
    assert "token.revoke      token rui" in capsys.readouterr().out


def test_serve_refuses_a_non_loopback_address_without_a_token(home, capsys):
    from learnest.service.cli.commands.registry import _loopback, _may_serve
    from learnest.service.config import Settings

    assert main(["serve", "--host", "0.0.0.0"]) == 2     # refused before anything listens
    err = capsys.readouterr().err
    assert "refusing to serve 0.0.0.0 with no token" in err and "--insecure" in err
    assert all(map(_loopback, ["127.0.0.1", "localhost", "::1", "[::1]", "127.0.0.2"]))
    assert not any(map(_loopback, ["0.0.0.0", "::", "192.168.1.5", "lab-server"]))
    settings = Settings(home=home)
    assert _may_serve(Namespace(host="0.0.0.0", insecure=True), settings)
    assert "anyone who reaches it" in capsys.readouterr().err
    assert _may_serve(Namespace(host="127.0.0.1", insecure=False), settings)
    assert _may_serve(Namespace(host="0.0.0.0", insecure=False), Settings(home=home, api_key="k"))
    assert main(["tokens", "create", "ada", "--scope", "admin"]) == 0
    assert _may_serve(Namespace(host="lab-server", insecure=False), settings)


def test_serve_names_the_starting_app_and_the_protocol_to_uvicorn(home, monkeypatch):
    """The CLI imports nothing of the app or the API: it names them to uvicorn by import path, and those paths
    are the starting app's factory and the deadline protocol, with the settings' limits beside them."""
    import importlib

    import uvicorn

    from learnest.service.api.server import DeadlineH11Protocol
    from learnest.service.app.starting import create_app

    runs = []
    monkeypatch.setattr(uvicorn, "run", lambda app, **options: runs.append((app, options)))
    for name in ("LEARNEST_LIMIT_CONCURRENCY", "LEARNEST_ALLOWED_HOSTS"):   # serve writes them: restored after
        monkeypatch.setenv(name, "1" if name.endswith("CONCURRENCY") else "testserver")
    assert main(["serve", "--port", "8765", "--limit-concurrency", "7"]) == 0
    [(app, options)] = runs

    def named(path):
        module, name = path.split(":")
        return getattr(importlib.import_module(module), name)

    assert named(app) is create_app and options["factory"] is True
    assert named(options["http"]) is DeadlineH11Protocol
    assert (options["host"], options["port"], options["workers"]) == ("127.0.0.1", 8765, 1)
    assert options["limit_concurrency"] == 7
