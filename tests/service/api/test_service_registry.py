"""The registry at MLflow's level: the evaluations list with MSE and improvement
columns, versions compared side by side, lineage as links, search by name, deletes that list their
dependents first, and the pages that show all of it.  Also /docs and /redoc without a CDN."""
import re
import time

import numpy as np
import pytest
from utils.service import EPOCHS, FAST_METHODS, blob_files, evaluate, flight_csv, running_app, train, upload


@pytest.fixture(scope="module")
def registry_app(tmp_path_factory):
    """flights A (training), B, C; quad:1 and quad:2 (lr differs, parent quad:1) trained on A, each evaluated
    on B and C; quad@production -> 2; an evaluation of quad:1 on B alone; a model named 'other'."""
    home = tmp_path_factory.mktemp("registry") / "home"
    logs = tmp_path_factory.mktemp("registry-logs")
    with running_app(home) as client:
        a, b, c = (upload(client, flight_csv(logs, seed)).json() for seed in (10, 11, 12))
        train(client, "quad", a["id"], hidden=8, lr=0.01)
        train(client, "quad", a["id"], hidden=8, lr=0.02, parent="quad:1")
        train(client, "other", a["id"], hidden=8)
        assert client.put("/models/quad/aliases/production", json={"version": 2}).status_code == 200
        reports = {}
        for ref in ("quad:1", "quad:2"):
            accepted, report = evaluate(client, ref, [b["id"], c["id"]])
            reports[ref] = (accepted["evaluation_id"], report)
        single, _ = evaluate(client, "quad:1", [b["id"]])  # answered from the results cache
        yield {"client": client, "home": home, "flights": (a, b, c), "reports": reports,
               "single": single["evaluation_id"]}


def test_the_evaluations_list_gives_mse_and_improvement_per_evaluation(registry_app):
    client, reports = registry_app["client"], registry_app["reports"]
    page = client.get("/evaluations").json()
    assert page["total"] == 3 and [e["id"] for e in page["items"]] == sorted((e["id"] for e in page["items"]),
                                                                             reverse=True)
    by_id = {e["id"]: e for e in page["items"]}
    for ref, (evaluation_id, report) in reports.items():
        item = by_id[evaluation_id]
        assert (item["model_ref"], item["model"], item["version"], item["state"]) == (ref, "quad", int(ref[-1]),
                                                                                      "succeeded")
        assert item["median_mse"] == report["median"] and item["flights_scored"] == 2
        # the improvement is the one the report computes from its medians: 100 (1 - KNODE / prior)
        expected = 100 * (1 - report["median"]["knode-ukf"] / report["median"]["ukf"])
        assert item["improvement_pct"]["knode-ukf_vs_ukf"] == pytest.approx(expected)
        assert item["links"]["report"] == f"/evaluations/{evaluation_id}/report.html"
        assert item["links"]["model_version"] == f"/models/quad/versions/{ref[-1]}"
    assert client.get("/evaluations", params={"q": "quad:2"}).json()["total"] == 1
    assert client.get("/evaluations", params={"model": "other"}).json()["total"] == 0
    paged = client.get("/evaluations", params={"limit": 1, "offset": 1}).json()
    assert paged["total"] == 3 and [e["id"] for e in paged["items"]] == [page["items"][1]["id"]]

    html = client.get("/ui/evaluations").text
    median = reports["quad:2"][1]["median"]
    assert f"{median['knode-ukf'] * 1e3:.3f}" in html and f"{median['ukf'] * 1e3:.3f}" in html
    improvement = reports["quad:2"][1]["improvement_pct"]["knode-ukf_vs_ukf"]
    assert f"{improvement:+.1f}" in html and "KNODE-UKF VS UKF (%)" in html
    assert f"href='/evaluations/{reports['quad:2'][0]}/report.html'" in html
    assert "href='/ui/models/quad/versions/2'" in html
    found = client.get("/ui/evaluations", params={"q": "quad:2"}).text
    assert f"/evaluations/{reports['quad:1'][0]}/report.html" not in found


def test_versions_side_by_side_on_the_flights_both_were_evaluated_on(registry_app):
    client, reports = registry_app["client"], registry_app["reports"]
    _, b, c = registry_app["flights"]
    out = client.get("/compare", params={"refs": "quad:1,quad@production"})
    assert out.status_code == 200, out.text
    compared = out.json()
    assert compared["refs"] == ["quad:1", "quad:2"]
    assert compared["hyperparameters"]["differs"] == ["lr"]
    assert compared["hyperparameters"]["values"]["lr"] == [0.01, 0.02]
    assert "best_validation_loss" in compared["metrics"]["values"]
    for version in compared["versions"]:
        assert len(version["losses"]) == EPOCHS and len(version["validation_losses"]) == EPOCHS
        assert all(np.isfinite(version["validation_losses"]))
    assert compared["methods"] == sorted(FAST_METHODS)
    assert [f["flight_id"] for f in compared["flights"]] == [b["id"], c["id"]]
    # the numbers are each version's own evaluation's, side by side
    for row in compared["flights"]:
        for k, ref in enumerate(("quad:1", "quad:2")):
            evaluation_id, report = reports[ref]
            entry = next(e for e in report["flights"] if e["flight_id"] == row["flight_id"])
            assert row["mse"]["knode-ukf"][k] == entry["mse"]["knode-ukf"]
            assert row["evaluations"][k] in (evaluation_id, registry_app["single"])
    for k, ref in enumerate(("quad:1", "quad:2")):
        assert compared["median_mse"]["ukf"][k] == pytest.approx(reports[ref][1]["median"]["ukf"])

    assert client.get("/compare", params={"refs": "quad:1"}).status_code == 422
    assert client.get("/compare", params={"refs": "quad:1,quad:1"}).status_code == 422
    assert client.get("/compare", params={"refs": "quad:1,quad:9"}).status_code == 404
    # versions never evaluated on the same flights: nothing side by side, said so
    assert client.get("/compare", params={"refs": "quad:1,other:1"}).json()["flights"] == []

    html = client.get("/ui/compare", params=[("refs", "quad:1"), ("refs", "quad:2")]).text
    assert "id='compare-flights'" in html and "id='compare-losses'" in html and "lr *" in html
    assert f"{compared['flights'][0]['mse']['knode-ukf'][1] * 1e3:.3f}" in html
    assert "no flight was scored" in client.get("/ui/compare", params={"refs": "quad:1,other:1"}).text
    assert "Error 422" in client.get("/ui/compare", params={"refs": "quad:1"}).text


def test_lineage_links_a_version_to_its_flight_parent_children_and_evaluations(registry_app):
    client, reports = registry_app["client"], registry_app["reports"]
    a, b, _ = registry_app["flights"]
    lineage = client.get("/models/quad/versions/2/lineage").json()
    assert lineage["training_flight"] == {"id": a["id"], "name": a["name"], "sha256": a["sha256"], "exists": True,
                                          "href": f"/flights/{a['id']}"}
    assert lineage["parent"] == {"ref": "quad:1", "exists": True, "href": "/models/quad/versions/1"}
    assert lineage["aliases"] == ["production"] and lineage["diagnosis"] is None
    assert [e["id"] for e in lineage["evaluations"]] == [reports["quad:2"][0]]
    assert client.get("/models/quad/versions/1/lineage").json()["children"] == \
        [{"ref": "quad:2", "href": "/models/quad/versions/2"}]
    assert len(client.get("/models/quad/versions/1").json()["validation_losses"]) == EPOCHS

    html = client.get("/ui/models/quad/versions/2").text
    assert f"id='training-flight' href='/ui/flights/{a['id']}'" in html
    assert "id='parent' href='/ui/models/quad/versions/1'" in html
    assert f"href='/evaluations/{reports['quad:2'][0]}/report.html'" in html
    assert f"href='/ui/flights/{b['id']}'" in html and "id='loss-curve'" in html
    model_page = client.get("/ui/models/quad").text
    assert "href='/ui/models/quad/versions/2'" in model_page and "value='quad:2' form='compare-form'" in model_page
    assert client.get("/ui/models/quad/versions/9").status_code == 404


def test_search_by_name(registry_app):
    client = registry_app["client"]
    a, b, _ = registry_app["flights"]
    assert [m["name"] for m in client.get("/models", params={"q": "QU"}).json()["items"]] == ["quad"]
    assert client.get("/models", params={"q": "%"}).json()["items"] == []   # a wildcard matches itself only
    found = client.get("/flights", params={"q": b["name"].upper()}).json()
    assert [f["id"] for f in found["items"]] == [b["id"]] and found["total"] == 1
    assert client.get("/flights", params={"q": "flight1"}).json()["total"] == 3
    models = client.get("/ui/models", params={"q": "oth"}).text
    assert "href='/ui/models/other'" in models and "href='/ui/models/quad'" not in models
    flights = client.get("/", params={"q": b["name"]}).text
    assert f"href='/ui/flights/{b['id']}'" in flights and f"href='/ui/flights/{a['id']}'>" not in flights


def test_openapi_docs_work_offline(registry_app):
    client = registry_app["client"]
    for path in ("/docs", "/redoc"):
        html = client.get(path)
        assert html.status_code == 200
        sources = re.findall(r"(?:src|href)=['\"]([^'\"]+)['\"]", html.text)
        assert sources and not [s for s in sources if "//" in s], sources  # no CDN, no other host
        for asset in sources:
            if asset.startswith("/docs-assets/"):
                got = client.get(asset)
                assert got.status_code == 200 and len(got.content) > 1000, asset
        assert "'/openapi.json'" in html.text or '"/openapi.json"' in html.text
    assert "/docs-assets/swagger-ui-bundle.js" in client.get("/docs").text
    assert "/docs-assets/redoc.standalone.js" in client.get("/redoc").text
    assert client.get("/docs/oauth2-redirect").status_code == 200


def _stages_while(client, job_id: int, timeout: float = 120.0) -> tuple[list[tuple], dict]:
    """(the distinct (stage, eta known) pairs seen while the job ran, the finished job)."""
    seen: list[tuple] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] not in ("queued", "running"):
            return seen, job
        if job["stage"] and (job["stage"], job["eta_s"] is not None) not in seen:
            seen.append((job["stage"], job["eta_s"] is not None))
            assert job["eta_s"] is None or 0 <= job["eta_s"] < 600
        time.sleep(0.02)
    raise AssertionError(f"job {job_id} did not finish")


def test_jobs_name_their_stage_with_an_eta_and_training_reports_both_times(registry_app):
    client = registry_app["client"]
    a, b, c = registry_app["flights"]
    epochs = 150   # about 3 s: several progress reports, one per second
    accepted = client.post("/models", json={"name": "staged", "flight_id": a["id"], "epochs": epochs, "hidden": 8})
    seen, job = _stages_while(client, accepted.json()["job_id"])
    assert job["state"] == "succeeded" and job["stage"] is None and job["eta_s"] is None   # only while running
    epochs_seen = [(stage, eta) for stage, eta in seen if stage.startswith("epoch ")]
    assert epochs_seen and all(re.fullmatch(rf"epoch \d+/{epochs}", stage) for stage, _ in epochs_seen)
    assert any(eta for _, eta in epochs_seen)            # the pace of the epochs gives an ETA
    stages, observer = [stage for stage, _ in seen], "observer (pre-training state estimates)"
    if observer in stages:   # seen only when the poll falls into it
        assert stages.index(observer) < stages.index(epochs_seen[0][0])
    # the epochs' time and the whole job's, both reported
    result = job["result"]
    assert 0 < result["seconds"] <= result["total_seconds"]
    assert f"training {result['seconds']:.1f} s (the epochs), {result['total_seconds']:.1f} s in all" in \
        client.get(f"/ui/jobs/{job['id']}").text

    response = client.post("/evaluations", json={"model": "staged:1", "flights": [b["id"], c["id"]],
                                                 "methods": FAST_METHODS})
    seen, job = _stages_while(client, response.json()["job_id"])
    assert job["state"] == "succeeded"
    method_stages = [stage for stage, _ in seen if " on " in stage]
    assert method_stages, seen
    names = {b["name"], c["name"]}
    for stage in method_stages:   # "knode-ukf on flight11 (2/2)", "ukf with mocap gaps on flight11 (1/2)"
        method, flight = re.fullmatch(r"(\S+)(?: with mocap gaps)? on (\S+) \([12]/2\)", stage).groups()
        assert method in FAST_METHODS and flight in names


def test_seconds_left_counts_down_from_the_estimate():
    from datetime import timedelta

    from learnest.service.jobs.runner import progress_values, seconds_left
    from learnest.service.storage.tables import Job

    values = progress_values(0.5, "epoch 5/10", 20.0)
    job = Job(state="running", **values)
    assert (job.progress, job.stage) == (0.5, "epoch 5/10")
    assert seconds_left(job, now=values["progress_at"] + timedelta(seconds=5)) == pytest.approx(15.0)
    assert seconds_left(job, now=values["progress_at"] + timedelta(seconds=50)) == 0.0
    assert progress_values(None, "ukf on f (1/2)") == {"stage": "ukf on f (1/2)"}   # the ETA stays
    assert progress_values(2.0)["progress"] == 1.0 and progress_values(0.3)["eta_s"] is None
    job.state = "succeeded"
    assert seconds_left(job) is None


# -- deletes (last: they change the module's registry) ---------------------------------------------------------
def test_an_evaluation_is_deleted_with_its_figures_and_its_job_stays(registry_app):
    client = registry_app["client"]
    evaluation_id = registry_app["single"]
    dependents = client.get(f"/evaluations/{evaluation_id}/dependents").json()
    assert dependents["blocked"] is None and not dependents["requires_force"]
    assert [d["kind"] for d in dependents["keeps_a_record"]] == ["job"]
    page = client.get(f"/ui/evaluations/{evaluation_id}/delete").text
    assert "id='delete-form'" in page and f"action='/ui/evaluations/{evaluation_id}/delete'" in page
    done = client.post(f"/ui/evaluations/{evaluation_id}/delete", follow_redirects=False)
    assert done.status_code == 303 and done.headers["location"] == "/ui/evaluations"
    assert client.get(f"/evaluations/{evaluation_id}").status_code == 404
    assert client.delete(f"/evaluations/{evaluation_id}").status_code == 404
    job_id = dependents["keeps_a_record"][0]["id"]
    assert client.get(f"/jobs/{job_id}").json()["state"] == "succeeded"


def test_a_version_with_evaluations_is_deleted_only_when_forced_and_its_number_is_never_reused(registry_app):
    client, home, reports = registry_app["client"], registry_app["home"], registry_app["reports"]
    a = registry_app["flights"][0]
    weights = client.get("/models/quad/versions/2").json()["weights_sha256"]
    dependents = client.get("/models/quad/versions/2/dependents").json()
    assert dependents["requires_force"] and dependents["blocked"] is None
    gone = {d["kind"] for d in dependents["deleted_with_it"]}
    assert gone == {"evaluation", "alias", "results"}
    assert [d["label"] for d in dependents["keeps_a_record"]] == []
    assert [d["ref"] for d in client.get("/models/quad/versions/1/dependents").json()["keeps_a_record"]] == \
        ["quad:2"]   # its child keeps "quad:1" as its parent

    refused = client.delete("/models/quad/versions/2")
    assert refused.status_code == 409 and f"evaluation {reports['quad:2'][0]}" in refused.json()["detail"]
    assert "quad@production" in refused.json()["detail"]
    assert client.get("/models/quad/versions/2").status_code == 200   # nothing was deleted
    confirm = client.get("/ui/models/quad/versions/2/delete").text
    assert f"evaluation {reports['quad:2'][0]} of quad:2" in confirm and "alias quad@production" in confirm

    assert client.post("/ui/models/quad/versions/2/delete", follow_redirects=False).status_code == 303
    assert client.get("/models/quad/versions/2").status_code == 404
    assert client.get(f"/evaluations/{reports['quad:2'][0]}").status_code == 404
    assert client.get("/models/quad").json()["aliases"] == {}
    assert weights not in blob_files(home)       # removed after the commit
    assert client.get(f"/evaluations/{reports['quad:1'][0]}").status_code == 200   # the other version's stays
    # quad:1 lost its child; a new version takes 3, never the deleted 2
    assert client.get("/models/quad/versions/1/lineage").json()["children"] == []
    assert train(client, "quad", a["id"], hidden=8)["version"] == 3


def test_a_flight_is_deleted_from_the_ui_after_its_dependents_are_shown(registry_app):
    client, home, reports = registry_app["client"], registry_app["home"], registry_app["reports"]
    a, b, _ = registry_app["flights"]
    confirm = client.get(f"/ui/flights/{a['id']}/delete").text
    assert "quad:1 was trained on it" in confirm and "id='delete-form'" in confirm
    dependents = client.get(f"/flights/{b['id']}/dependents").json()
    assert not dependents["requires_force"]
    assert [d["kind"] for d in dependents["deleted_with_it"]] == ["results"]
    assert f"evaluation {reports['quad:1'][0]}" in " ".join(d["label"] for d in dependents["keeps_a_record"])
    blob = client.get(f"/flights/{a['id']}").json()["sources"][0]["sha256"]
    done = client.post(f"/ui/flights/{a['id']}/delete", follow_redirects=False)
    assert done.status_code == 303 and done.headers["location"] == "/"
    assert client.get(f"/flights/{a['id']}").status_code == 404 and blob not in blob_files(home)
    lineage = client.get("/models/quad/versions/1/lineage").json()["training_flight"]
    assert lineage["exists"] is False and lineage["name"] == a["name"]   # the version keeps its lineage
    assert "(flight {}, deleted)".format(a["id"]) in client.get("/ui/models/quad/versions/1").text
