"""Tokens with scopes on every route group, on SQLite and on PostgreSQL (a throwaway server, skipped without
initdb): no token gets 401 once a token exists, read tokens cannot write, write tokens cannot delete, admin
tokens can; revoked tokens fail on the next request, on another server worker too; rows record the token
that made them; deletes and token changes are in the audit log and stay there after the rows are gone."""
from __future__ import annotations

import pytest
from utils.service import EPOCHS, FAST_METHODS, flight_csv, running_app, upload

from learnest.service.storage.tables import Diagnosis, Evaluation, FlightRecord, ModelVersion


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def database(request) -> dict:
    """Settings of the app's database: its SQLite file, or a throwaway PostgreSQL server."""
    return {} if request.param == "sqlite" else {"database_url": request.getfixturevalue("postgres_url")}


def bearer(token: str) -> dict:
    return {"Authorization": f"Bearer {token}"}


def make_tokens(client) -> dict[str, str]:
    """On an open server, the first admin token (anyone may make it), then a write and a read token."""
    made = {"admin": client.post("/tokens", json={"name": "ada", "scope": "admin"})}
    for name, scope in (("wes", "write"), ("rui", "read")):
        made[scope] = client.post("/tokens", json={"name": name, "scope": scope},
                                  headers=bearer(made["admin"].json()["token"]))
    assert all(r.status_code == 201 for r in made.values()), [r.text for r in made.values()]
    return {scope: r.json()["token"] for scope, r in made.items()}


# one GET per route group, and the writes and deletes of each group (bodies that pass the guard)
READS = ["/flights", "/flights/1", "/flights/1/raw", "/flights/1/data", "/models", "/models/m",
         "/models/m/versions/1/weights", "/compare?refs=m:1&refs=m:1", "/jobs", "/jobs/1", "/evaluations",
         "/evaluations/1", "/evaluations/1/report.html", "/diagnoses/1", "/openapi.json", "/docs", "/", "/ui/models",
         "/ui/flights/1", "/ui/jobs", "/ui/evaluations", "/whoami"]
WRITES = [("post", "/models", {"name": "n", "flight_id": 1, "epochs": 1}),
          ("post", "/evaluations", {"model": "m:1", "flights": [1], "methods": ["ukf"]}),
          ("post", "/diagnoses", {"flights": [999]}),
          ("put", "/models/m/aliases/production", {"version": 1}),
          ("post", "/jobs/999/cancel", None)]
DELETES = ["/evaluations/1", "/models/m/aliases/production", "/models/m/versions/1?force=true", "/flights/1",
           "/tokens/999"]
ADMIN_READS = ["/tokens", "/audit"]


def _send(client, method: str, url: str, body, headers: dict):
    kwargs = {"json": body} if body is not None else {}
    return client.request(method.upper(), url, headers=headers, **kwargs)


def test_each_scope_on_every_route_group(tmp_path, data_dir, database):
    with running_app(tmp_path / "home", **database) as client:
        assert client.get("/flights").status_code == 200            # open until a token exists
        tokens = make_tokens(client)
        writer, reader, admin = bearer(tokens["write"]), bearer(tokens["read"]), bearer(tokens["admin"])

        flight = upload(client, flight_csv(data_dir, 0), headers=writer)
        assert flight.status_code == 201 and flight.json()["created_by"] == "wes"
        trained = client.post("/models", json={"name": "m", "flight_id": 1, "epochs": EPOCHS}, headers=writer)
        assert trained.status_code == 202
        assert wait(client, trained.json()["job_id"], writer) == "succeeded"
        evaluation = client.post("/evaluations", json={"model": "m:1", "flights": [1], "methods": FAST_METHODS},
                                 headers={"X-API-Key": tokens["write"]})       # the other header
        assert evaluation.status_code == 202
        assert wait(client, evaluation.json()["job_id"], writer) == "succeeded"

        # no token: 401 everywhere but /health
        assert client.get("/health").status_code == 200
        for url in READS + ADMIN_READS:
            assert client.get(url).status_code == 401, url
        assert upload(client, flight_csv(data_dir, 1)).status_code == 401
        for method, url, body in WRITES:
            assert _send(client, method, url, body, {}).status_code == 401, url
        for url in DELETES:
            assert client.delete(url).status_code == 401, url

        # read: every GET; no write, no delete, no tokens
        for url in READS:
            assert client.get(url, headers=reader).status_code not in (401, 403), url
        assert client.get("/whoami", headers=reader).json() == {"name": "rui", "scope": "read", "signed_in": True}
        assert upload(client, flight_csv(data_dir, 1), headers=reader).status_code == 403
        for method, url, body in WRITES:
            refused = _send(client, method, url, body, reader)
            assert refused.status_code == 403 and "needs a token of scope write" in refused.json()["detail"], url
        for url in DELETES + ADMIN_READS:
            assert _send(client, "delete" if url in DELETES else "get", url, None, reader).status_code == 403, url

        # write: writes pass the guard (what the route then says is the route's), deletes and tokens do not
        answers = {url: _send(client, method, url, body, writer) for method, url, body in WRITES}
        assert {url: r.status_code for url, r in answers.items()} == {
            "/models": 202, "/evaluations": 202, "/diagnoses": 404, "/models/m/aliases/production": 200,
            "/jobs/999/cancel": 404}
        for url in ("/models", "/evaluations"):    # finished before the deletes (a running one blocks them)
            assert wait(client, answers[url].json()["job_id"], writer) in ("succeeded", "failed")
        for url in DELETES + ADMIN_READS:
            refused = _send(client, "delete" if url in DELETES else "get", url, None, writer)
            assert refused.status_code == 403 and "scope admin" in refused.json()["detail"], url
        assert client.post("/tokens", json={"name": "x", "scope": "admin"}, headers=writer).status_code == 403

        # who made what
        db = client.app.state.services.db
        with db.transaction() as session:
            assert {r.created_by for r in session.query(FlightRecord)} == {"wes"}
            assert {r.created_by for r in session.query(ModelVersion)} == {"wes"}
            assert {r.created_by for r in session.query(Evaluation)} == {"wes"}

        # admin: deletes; the audit log names who, and keeps it after the rows are gone
        for url in DELETES[:-1]:
            assert client.delete(url, headers=admin).status_code == 204, url
        entries = client.get("/audit", headers=admin).json()["items"]
        deleted = [(e["actor"], e["action"]) for e in entries if e["action"].endswith(".delete")]
        assert deleted == [("ada", "flight.delete"), ("ada", "version.delete"), ("ada", "alias.delete"),
                           ("ada", "evaluation.delete")]
        assert ("wes", "alias.set") in [(e["actor"], e["action"]) for e in entries]
        assert client.get("/flights", headers=admin).json()["total"] == 0


def wait(client, job_id: int, headers: dict, timeout: float = 120.0) -> str:
    """The final state of a job, polled with ``headers``."""
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        state = client.get(f"/jobs/{job_id}", headers=headers).json()["state"]
        if state in ("succeeded", "failed", "cancelled"):
            return state
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} still {state} after {timeout} s")


def test_a_revoked_token_fails_at_once_on_every_worker(tmp_path, database):
    with running_app(tmp_path / "home", **database) as one, running_app(tmp_path / "home", **database) as other:
        tokens = make_tokens(one)
        reader = bearer(tokens["read"])
        assert one.get("/flights", headers=reader).status_code == 200
        assert other.get("/flights", headers=reader).status_code == 200      # the other worker knows it too
        rows = {t["name"]: t["id"] for t in one.get("/tokens", headers=bearer(tokens["admin"])).json()}
        revoked = other.delete(f"/tokens/{rows['rui']}", headers=bearer(tokens["admin"]))
        assert revoked.status_code == 200 and revoked.json()["revoked_by"] == "ada"
        for client in (one, other):
            refused = client.get("/flights", headers=reader)
            assert refused.status_code == 401 and "not valid" in refused.json()["detail"]
        assert one.delete(f"/tokens/{rows['rui']}", headers=bearer(tokens["admin"])).status_code == 409
        # its name may be given again; the old token stays revoked
        again = one.post("/tokens", json={"name": "rui", "scope": "read"}, headers=bearer(tokens["admin"]))
        assert again.status_code == 201 and one.get("/flights", headers=reader).status_code == 401
        log = [(e["action"], e["target"]) for e in one.get("/audit", headers=bearer(tokens["admin"])).json()["items"]]
        assert log[:2] == [("token.create", "token rui"), ("token.revoke", "token rui")]


def test_revoking_every_token_keeps_the_server_private(tmp_path):
    with running_app(tmp_path / "home") as client:
        token = make_tokens(client)["admin"]
        for row in client.get("/tokens", headers=bearer(token)).json()[::-1]:   # the admin's own last
            assert client.delete(f"/tokens/{row['id']}", headers=bearer(token)).status_code == 200
        assert client.get("/flights").status_code == 401


def test_failed_tokens_count_toward_the_throttle_and_the_right_one_passes(tmp_path):
    with running_app(tmp_path / "home", key_failures=3) as client:
        tokens = make_tokens(client)
        for _ in range(3):
            assert client.get("/flights", headers=bearer("lnst_guess")).status_code == 401
        throttled = client.get("/flights", headers=bearer("lnst_guess"))
        assert throttled.status_code == 429 and int(throttled.headers["retry-after"]) >= 1
        assert client.get("/flights", headers=bearer(tokens["read"])).status_code == 200


def test_public_reads_open_the_reads_only(tmp_path, data_dir):
    with running_app(tmp_path / "home", api_key="k3y", public_reads=True) as client:
        assert client.get("/flights").status_code == 200
        assert client.get("/whoami").json() == {"name": "anonymous", "scope": "read", "signed_in": False}
        assert upload(client, flight_csv(data_dir, 0)).status_code == 401
        assert client.get("/tokens").status_code == 401 and client.get("/audit").status_code == 401
        assert upload(client, flight_csv(data_dir, 0), headers={"X-API-Key": "k3y"}).json()["created_by"] == "api-key"


def test_token_names_and_scopes_are_checked(tmp_path):
    with running_app(tmp_path / "home", api_key="k3y") as client:
        key = {"X-API-Key": "k3y"}
        assert client.post("/tokens", json={"name": "ok", "scope": "owner"}, headers=key).status_code == 422
        bad = client.post("/tokens", json={"name": "1st", "scope": "read"}, headers=key)
        assert bad.status_code == 422 and "token name '1st'" in bad.json()["detail"]
        assert client.post("/tokens", json={"name": "api-key", "scope": "read"}, headers=key).status_code == 422
        assert client.post("/tokens", json={"name": "ok", "scope": "read"}, headers=key).status_code == 201
        assert client.post("/tokens", json={"name": "ok", "scope": "read"}, headers=key).status_code == 409
        listed = client.get("/tokens", headers=key).json()
        assert [t["name"] for t in listed] == ["ok"] and "token" not in listed[0] and "token_hash" not in listed[0]


def test_only_a_hash_of_the_token_is_stored(tmp_path):
    from learnest.service.storage.tables import ApiToken
    from learnest.service.storage.tokens import hash_token

    with running_app(tmp_path / "home") as client:
        tokens = make_tokens(client)
        with client.app.state.services.db.transaction() as session:
            stored = {row.token_hash for row in session.query(ApiToken)}
    assert stored == {hash_token(t) for t in tokens.values()} and not stored & set(tokens.values())


def test_a_diagnosis_records_its_token(tmp_path, data_dir):
    with running_app(tmp_path / "home") as client:
        writer = bearer(make_tokens(client)["write"])
        upload(client, flight_csv(data_dir, 0), headers=writer)
        upload(client, flight_csv(data_dir, 1), headers=writer)
        started = client.post("/diagnoses", json={"flights": [1, 2], "epochs": 1, "methods": ["ukf"]},
                              headers=writer)
        assert started.status_code == 202, started.text
        with client.app.state.services.db.transaction() as session:
            assert session.get(Diagnosis, started.json()["diagnosis_id"]).created_by == "wes"
        client.post(f"/jobs/{started.json()['job_id']}/cancel", headers=writer)
