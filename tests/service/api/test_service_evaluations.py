"""HTTP service, /evaluations: batch evaluation as a job equals workflows.flights.evaluate_flights, the
results cache, the HTML report, the scheduler (and `learnest evaluate --new`), and the Dask executor."""
import dataclasses
import json
import re
import time

import pytest
from utils.service import (
    FAST_METHODS,
    evaluate,
    flight_csv,
    running_app,
    settings_for,
    train,
    upload,
    wait_for_job,
    without_timing,
)

from learnest.ingest.flight import Flight as CanonicalFlight


@pytest.fixture(scope="module")
def registry_home(tmp_path_factory):
    """Three clean flights, quad:1 trained on the first one and aliased production."""
    root = tmp_path_factory.mktemp("evaluations")
    home, logs = root / "home", root / "logs"
    logs.mkdir()
    with running_app(home) as client:
        ids = [upload(client, flight_csv(logs, seed)).json()["id"] for seed in (0, 1, 2)]
        train(client, "quad", ids[0])
        assert client.put("/models/quad/aliases/production", json={"version": 1}).status_code == 200
    return {"home": home, "logs": logs, "ids": ids, "training": ids[0]}


def stored_flights(home, ids) -> list[CanonicalFlight]:
    from sqlalchemy import select

    from learnest.service.storage.blobs import BlobStore
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import FlightRecord

    database, blobs = Database(settings_for(home).url), BlobStore(home / "blobs")
    with database.transaction() as session:
        query = select(FlightRecord).where(FlightRecord.id.in_(ids))
        rows = {row.id: row.flight_blob for row in session.scalars(query)}
    database.dispose()
    return [CanonicalFlight.from_bytes(blobs.read_bytes(rows[i])) for i in ids]


def assert_same_numbers(report: dict, expected: dict) -> None:
    assert [f["flight"] for f in report["flights"]] == [f["flight"] for f in expected["flights"]]
    for got, want in zip(report["flights"], expected["flights"]):
        assert got["excluded"] == want["excluded"] and got["reason"] == want["reason"]
        assert got["mse"] == pytest.approx(want["mse"], rel=1e-9, abs=1e-15)
        for method in want["groups"]:
            assert got["groups"][method] == pytest.approx(want["groups"][method], rel=1e-9, abs=1e-15)
    assert report["median"] == pytest.approx(expected["median"], rel=1e-9)
    assert report["improvement_pct"] == pytest.approx(expected["improvement_pct"], rel=1e-6, abs=1e-9)
    assert report["flights_scored"] == expected["flights_scored"]
    for got, want in zip(report["flights"], expected["flights"]):
        assert got.get("envelope") == want.get("envelope")
        assert got.get("one_step_innovation_ratio") == pytest.approx(want.get("one_step_innovation_ratio"), rel=1e-9)
        assert got.get("verdict") == want.get("verdict")
    assert report["outside_training_envelope"] == expected["outside_training_envelope"]
    assert report["verdicts"] == expected["verdicts"]
    for got, want in zip(report["flights"], expected["flights"]):
        assert got.get("gain_interval_pct") == want.get("gain_interval_pct")
    assert (report["recommended"] is None) == (expected["recommended"] is None)
    if expected["recommended"] is not None:
        assert report["recommended"]["prior_on"] == expected["recommended"]["prior_on"]
        assert report["recommended"]["knode_on"] == expected["recommended"]["knode_on"]
        assert report["recommended"]["median_gap_rmse_m"] == pytest.approx(
            expected["recommended"]["median_gap_rmse_m"], rel=1e-9)


def test_report_equals_evaluate_flights_and_is_cached(registry_home):
    from learnest.service.storage.registry import load_model_ref
    from learnest.workflows.flights import evaluate_flights

    home, ids = registry_home["home"], registry_home["ids"]
    with running_app(home) as client:
        accepted, report = evaluate(client, "quad@production", "all-other")
        assert set(report) >= {"model", "flights", "median", "improvement_pct"}
        assert report["model"] == "quad:1" and len(report["flights"]) == 2
        assert set(report["flights"][0]) >= {"flight", "excluded", "reason", "mse", "groups"}

        model = load_model_ref("quad:1", settings_for(home))
        direct = json.loads(json.dumps(evaluate_flights(model, stored_flights(home, ids[1:]), FAST_METHODS)))
        assert_same_numbers(report, direct)

        # asking again: answered from the results table, the job is done in the 202 itself
        again = client.post("/evaluations", json={"model": "quad:1", "flights": ids[1:], "methods": FAST_METHODS})
        assert again.status_code == 202 and again.json()["state"] == "succeeded"
        cached = client.get(f"/evaluations/{again.json()['evaluation_id']}").json()
        assert cached["flights"] == report["flights"]           # same entries, ms_per_step included
        assert client.get(f"/jobs/{again.json()['job_id']}").json()["result"]["computed"] == 0

        # the training flight is never scored on its own data; only uncached flights are computed
        _, with_training = evaluate(client, "quad:1", ids, methods=FAST_METHODS)
        assert with_training["flights"][0]["excluded"] is True
        assert with_training["flights"][0]["reason"].startswith("training flight")
        assert with_training["flights"][1:] == report["flights"]

        html = client.get(f"/evaluations/{accepted['evaluation_id']}/report.html")
        assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
        assert "data:image/png;base64," in html.text and report["flights"][0]["flight"] in html.text
        assert "outside what this model saw" in html.text      # the training-envelope column
        assert "prediction-check" not in html.text and "Do not trust" not in html.text   # one verdict, the gaps'
        recommended_ukf = report["recommended"]["median_gap_rmse_m"]["ukf"]
        assert "id='recommended'" in html.text and f"median gap RMSE {recommended_ukf * 1e3:.1f} mm" in html.text
        low, high = report["flights"][1]["gain_interval_pct"]["knode-ukf_vs_ukf"]
        assert low <= high and "id='gain-intervals'" in html.text and f"[{low:+.1f}, {high:+.1f}] %" in html.text
        assert report["flights"][0]["envelope"]["threshold"] > 0
        # the envelope is stored with the version (registry metadata), not only in the weights file
        metrics = client.get("/models/quad").json()
        assert "envelope" in json.dumps(metrics)


def test_mhe_numbers_equal_evaluate_flights(registry_home):
    from learnest.service.storage.registry import load_model_ref
    from learnest.workflows.flights import evaluate_flights

    home, flight_id = registry_home["home"], registry_home["ids"][1]
    methods = ["mhe", "knode-mhe"]
    with running_app(home) as client:
        _, report = evaluate(client, "quad:1", [flight_id], methods=methods, horizon=10)
    model = load_model_ref("quad:1", settings_for(home))
    direct = evaluate_flights(model, stored_flights(home, [flight_id]), methods, horizon=10)
    assert_same_numbers(report, json.loads(json.dumps(direct)))


def test_dask_executor_gives_the_local_pool_numbers(registry_home):
    from sqlalchemy import delete

    from learnest.service.jobs.executors import DaskExecutor
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import Result

    home, ids = registry_home["home"], registry_home["ids"]
    request = {"model": "quad:1", "flights": ids[1:], "methods": FAST_METHODS, "horizon": 7}
    with running_app(home) as client:
        local = evaluate(client, request["model"], request["flights"], horizon=7)[1]
    database = Database(settings_for(home).url)
    with database.transaction() as session:  # forget the cache so Dask really computes
        session.execute(delete(Result))
    database.dispose()
    executor = DaskExecutor(processes=False, n_workers=1, threads_per_worker=1)
    try:
        with running_app(home, executor=executor) as client:
            assert client.get("/health").json()["executor"]["name"] == "dask"
            accepted = client.post("/evaluations", json=request).json()
            assert accepted["state"] == "queued"   # computed, not cached
            dask_report = evaluate(client, request["model"], request["flights"], horizon=7)[1]
            assert wait_for_job(client, accepted["job_id"])["state"] == "succeeded"  # not cut off by the exit
    finally:
        executor.shutdown()
    assert without_timing(dask_report) == without_timing(local)


def test_scheduler_evaluates_new_flights_once(registry_home, monkeypatch, capsys):
    from sqlalchemy import select

    from learnest.service.cli import main as cli_main
    from learnest.service.jobs.result_cache import EstimatorSettings
    from learnest.service.jobs.runner import JobRunner
    from learnest.service.jobs.scheduler import Scheduler
    from learnest.service.storage.tables import FlightRecord, Result

    home, logs = registry_home["home"], registry_home["logs"]
    fast = EstimatorSettings(tuple(FAST_METHODS))
    with running_app(home) as client:
        services = client.app.state.services
        scheduler = Scheduler(services, interval_s=3600, alias="production", settings=fast)
        first = scheduler.tick()
        assert len(first) == 1 and first[0]["model"] == "quad:1" and first[0]["state"] == "succeeded"
        assert first[0]["flights"] == registry_home["ids"]            # nothing had these settings yet
        assert scheduler.tick() == []                                   # ... and now everything has

        # only one process schedules: another owner cannot take the lease while it is held
        rival = Scheduler(dataclasses.replace(services, runner=JobRunner(services.db)), 3600, settings=fast)
        assert rival.tick() is None

        # two new flights, one of which cannot be evaluated (its stored flight is corrupt)
        new_ok = upload(client, flight_csv(logs, 7)).json()
        broken = upload(client, flight_csv(logs, 8)).json()
        blobs = services.blobs
        database = services.db
        with database.transaction() as session:
            blob = session.get(FlightRecord, broken["id"]).flight_blob
        blobs.path(blob).write_bytes(b"not a flight any more")
        second = scheduler.tick()
        assert len(second) == 1 and second[0]["flights"] == [new_ok["id"], broken["id"]]
        assert second[0]["state"] == "succeeded" and second[0]["failed"] == 1
        report = client.get(f"/evaluations/{second[0]['evaluation_id']}").json()
        ok_entry, failed_entry = report["flights"]
        assert ok_entry["excluded"] is False and set(ok_entry["mse"]) == set(FAST_METHODS)
        assert failed_entry["excluded"] is True and failed_entry["reason"].startswith("failed: ")
        with database.transaction() as session:
            states = {r.flight_id: r.state for r in session.scalars(select(Result))}
        assert states[new_ok["id"]] == "succeeded" and states[broken["id"]] == "failed"
        assert scheduler.tick() == []                  # a recorded failure is not retried every interval
        scheduler.stop()

        # `learnest evaluate --new` (cron) does one round the same way
        assert client.delete(f"/flights/{broken['id']}").status_code == 204
        newest = upload(client, flight_csv(logs, 9)).json()
    monkeypatch.setenv("LEARNEST_HOME", str(home))
    monkeypatch.setenv("LEARNEST_POOL_WORKERS", "1")
    monkeypatch.delenv("LEARNEST_DATABASE_URL", raising=False)
    capsys.readouterr()
    assert cli_main(["evaluate", "--new", "--methods", ",".join(FAST_METHODS), "--json"]) == 0
    rounds = json.loads(capsys.readouterr().out)["evaluations"]
    assert [(r["model"], r["flights"], r["state"]) for r in rounds] == [("quad:1", [newest["id"]], "succeeded")]


def test_cli_evaluate_new_output(registry_home, monkeypatch, capsys):
    """Runs after the scheduler test: the CLI already evaluated the newest flight, so nothing is left."""
    from learnest.service.cli import main as cli_main

    monkeypatch.setenv("LEARNEST_HOME", str(registry_home["home"]))
    monkeypatch.delenv("LEARNEST_DATABASE_URL", raising=False)
    assert cli_main(["evaluate", "--new", "--methods", ",".join(FAST_METHODS), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out == {"alias": "production", "busy": False, "evaluations": []}
    assert cli_main(["evaluate", "--new", "--alias", "nobody-has-this", "--methods", "ukf"]) == 0
    assert "nothing new" in capsys.readouterr().out
    assert cli_main(["evaluate", "--model", "x"]) == 2   # the old form still needs files


def test_the_report_page_computes_its_velocity_figure_once_and_keeps_it(registry_home):
    """For an evaluation whose estimates were not stored (made before they were kept): a
    report view starts one executor task for the figure (never a second one while it runs, however many
    views), the page reloads until it is stored, and later views read the stored one."""
    from sqlalchemy import func, select, update

    from learnest.service.jobs.result_cache import EstimatorSettings
    from learnest.service.storage.tables import ReportFigure, Result
    from learnest.service.web import report_figures

    home, ids = registry_home["home"], registry_home["ids"]
    with running_app(home) as client:
        accepted, _ = evaluate(client, "quad:1", [ids[2]], methods=["ukf"])   # settings no other test uses
        page_url = f"/evaluations/{accepted['evaluation_id']}/report.html"
        assert "id='error-plot'" in client.get(page_url).text              # drawn from the stored estimates
        only_this = Result.settings_key == EstimatorSettings(("ukf",)).key
        with client.app.state.services.db.transaction() as session:          # as before estimates were kept
            kept = session.scalar(select(Result.estimates_blob).where(only_this))
            session.execute(update(Result).where(only_this).values(estimates_blob=None))
        first = [client.get(page_url) for _ in range(5)]
        assert all(r.status_code == 200 and "being computed" in r.text and "http-equiv='refresh'" in r.text
                   or "velocity-plot" in r.text for r in first)
        assert len(report_figures._running) <= 1
        deadline = time.monotonic() + 60
        while "id='velocity-plot'" not in (answer := client.get(page_url)).text:
            assert time.monotonic() < deadline, answer.text[-500:]
            time.sleep(0.2)
        assert "being computed" not in answer.text and "http-equiv='refresh'" not in answer.text
        services = client.app.state.services
        with services.db.transaction() as session:
            stored = session.scalar(select(func.count()).select_from(ReportFigure)
                                    .where(ReportFigure.evaluation_id == accepted["evaluation_id"]))
        assert stored == 1
        started = time.monotonic()
        assert "id='velocity-plot'" in client.get(page_url).text and time.monotonic() - started < 2
        with services.db.transaction() as session:
            session.execute(update(Result).where(only_this).values(estimates_blob=kept))


def embedded_figure(html: str, plot_id: str) -> dict:
    """The figure spec a report page embeds for static/plots.js (a JSON script block)."""
    start = html.index(f"data-plot='{plot_id}'>") + len(f"data-plot='{plot_id}'>")
    return json.loads(html[start:html.index("</script>", start)])


def test_report_plots_come_from_the_stored_estimates_with_the_chosen_sg_window(registry_home):
    """The report's time series are the stored estimates minus the reference (per group),
    the paired dots are the table's MSE x 1e3, the SG window is a setting (its own cache key) shown on the
    page, plotly.js is served by the server itself; the flight page embeds its channels the same way."""
    import io

    import numpy as np
    import pandas as pd

    home, ids = registry_home["home"], registry_home["ids"]
    with running_app(home) as client:
        accepted, report = evaluate(client, "quad:1", ids[1:], sg_window=51)
        assert client.get(f"/evaluations/{accepted['evaluation_id']}").status_code == 200
        assert client.get(f"/jobs/{accepted['job_id']}").json()["result"]["computed"] == 2  # not the 150 cache
        _, default = evaluate(client, "quad:1", ids[1:])
        assert report["flights"][0]["mse"]["ukf"] != pytest.approx(default["flights"][0]["mse"]["ukf"], rel=1e-3)

        url = f"/evaluations/{accepted['evaluation_id']}/report.html"
        html = client.get(url, params={"flight": ids[2], "group": "a"}).text
        assert "Savitzky-Golay reference window 51 samples" in html and "id='sg-caveat'" in html
        text = re.sub(r"data:image/png;base64,[^']*", "", html)   # a PNG's base64 can spell anything
        assert "/vendor/plotly.min.js" in html and "/static/plots.js" in html and "cdn" not in text.lower()
        spec = embedded_figure(html, "error-plot")
        frame = pd.read_csv(io.BytesIO(client.get(f"/evaluations/{accepted['evaluation_id']}/estimates",
                                                  params={"flight": ids[2]}).content))
        ukf = frame[frame["method"] == "ukf"]
        error_x = [t for t in spec["data"] if t["name"] == "UKF" and t["yaxis"] == "y2"]
        assert len(error_x) == 1 and len(spec["t"]) == len(ukf)
        np.testing.assert_allclose(error_x[0]["y"], ukf["err_a_x_m_s2"], rtol=1e-4, atol=1e-9)
        assert spec["layout"]["yaxis2"]["title"]["text"] == "ax error (m/s²)"

        paired = embedded_figure(html, "paired-plot")
        lines = [t for t in paired["data"] if t.get("text")]
        assert len(lines) == 2 * 4    # 2 flights x 4 panels (overall, p, v, a) of the one pair run
        entry = report["flights"][1]
        overall = [t for t in lines if t["xaxis"] == "x" and t["text"][0] == entry["flight"]]
        assert overall[0]["y"] == pytest.approx([entry["mse"]["ukf"] * 1e3, entry["mse"]["knode-ukf"] * 1e3])

        assert client.get(url, params={"group": "q"}).status_code == 422
        bad = client.post("/evaluations", json={"model": "quad:1", "flights": ids[1:], "sg_window": 2})
        assert bad.status_code == 422 and "sg_window" in bad.text
        flight_page = client.get(f"/ui/flights/{ids[1]}").text      # the flight page's channels, same script
        channels = embedded_figure(flight_page, "channels-plot")
        assert "<script src='/vendor/plotly.min.js'></script>" in flight_page
        assert {t["name"] for t in channels["data"]} >= {"x", "y", "z", "roll", "pitch", "yaw"}
        assert any(s["x0"] == 0.0 and s["fillcolor"] == "#999999" for s in channels["layout"]["shapes"])  # take-off
        assert client.get("/static/plots.js").status_code == 200
        js = client.get("/vendor/plotly.min.js")
        assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript")
        assert "plotly" in js.text[:2000].lower() and len(js.content) > 1e6


def test_estimates_download_as_csv_parquet_and_mcap(registry_home):
    """GET /evaluations/{id}/estimates through the real app: the tidy table reproduces the reported MSE, one
    flight can be chosen, errors are 400/404/409; results cached before estimates were kept are computed
    again; deleting a flight deletes its stored estimates.  (Last in the module: it deletes a flight.)"""
    import io

    import numpy as np
    import pandas as pd
    import pyarrow.parquet as pq
    from mcap.reader import make_reader
    from sqlalchemy import select, update
    from utils.service import blob_files

    from learnest.estimators.estimates import STATE_COLUMNS
    from learnest.service.storage.tables import Result

    home, ids = registry_home["home"], registry_home["ids"]
    with running_app(home) as client:
        accepted, report = evaluate(client, "quad:1", ids[1:])
        evaluation_id = accepted["evaluation_id"]
        shas = [client.get(f"/flights/{i}").json()["sha256"] for i in ids[1:]]
        assert [(f["flight_id"], f["sha256"]) for f in report["flights"]] == list(zip(ids[1:], shas))
        assert report["units"]["groups"] == {"p": "m^2", "v": "m^2/s^2", "a": "m^2/s^4"}

        response = client.get(f"/evaluations/{evaluation_id}/estimates?format=csv")
        assert response.status_code == 200 and response.headers["content-type"].startswith("text/csv")
        assert f'filename="evaluation-{evaluation_id}-estimates.csv"' in response.headers["content-disposition"]
        frame = pd.read_csv(io.BytesIO(response.content))
        assert sorted(set(frame["flight_id"])) == ids[1:] and sorted(set(frame["method"])) == sorted(FAST_METHODS)
        for entry in report["flights"]:  # the exported errors give back the reported MSE of every method
            for method in FAST_METHODS:
                rows = frame[(frame["flight_id"] == entry["flight_id"]) & (frame["method"] == method)]
                errors = rows[[f"err_{c}" for c in STATE_COLUMNS]].to_numpy()
                assert np.mean(errors ** 2) == pytest.approx(entry["mse"][method], rel=1e-9)
                assert rows["flight"].iloc[0] == entry["flight"]

        one = client.get(f"/evaluations/{evaluation_id}/estimates", params={"format": "parquet", "flight": ids[2]})
        assert one.status_code == 200
        assert f"evaluation-{evaluation_id}-flight-{ids[2]}-estimates.parquet" in one.headers["content-disposition"]
        table = pq.read_table(io.BytesIO(one.content))
        assert set(table.column("flight_id").to_pylist()) == {ids[2]}
        assert table.schema.field("a_x_m_s2").metadata[b"unit"] == b"m/s^2"

        mcap = client.get(f"/evaluations/{evaluation_id}/estimates", params={"format": "mcap", "flight": ids[1]})
        summary = make_reader(io.BytesIO(mcap.content)).get_summary()
        topics = {c.topic for c in summary.channels.values()}
        assert {"/learnest/ukf/velocity", "/learnest/knode-ukf/pose", "/learnest/reference/velocity"} <= topics
        samples = int((frame["flight_id"] == ids[1]).sum() / len(FAST_METHODS))
        assert summary.statistics.message_count == samples * len(topics)

        assert client.get(f"/evaluations/{evaluation_id}/estimates?format=xlsx").json() == \
            {"detail": "unknown format 'xlsx'; choose one of csv, parquet, mcap"}
        assert client.get(f"/evaluations/{evaluation_id}/estimates?format=xlsx").status_code == 400
        assert client.get("/evaluations/999999/estimates").status_code == 404
        not_in = client.get(f"/evaluations/{evaluation_id}/estimates", params={"flight": ids[0]})
        assert not_in.status_code == 404 and "not one of evaluation" in not_in.json()["detail"]
        page = client.get(f"/evaluations/{evaluation_id}/report.html").text
        assert f"/evaluations/{evaluation_id}/estimates?format=mcap" in page

        # a result cached before estimates were kept: the download says so, a new evaluation computes it again
        database = client.app.state.services.db
        with database.transaction() as session:
            session.execute(update(Result).where(Result.flight_sha256 == shas[0]).values(estimates_blob=None))
        stale = client.get(f"/evaluations/{evaluation_id}/estimates")
        assert stale.status_code == 409 and "evaluate them again" in stale.json()["detail"]
        again = client.post("/evaluations", json={"model": "quad:1", "flights": ids[1:], "methods": FAST_METHODS})
        assert again.json()["state"] == "queued"            # not answered from the cache
        assert wait_for_job(client, again.json()["job_id"])["state"] == "succeeded"
        assert client.get(f"/evaluations/{again.json()['evaluation_id']}/estimates").status_code == 200

        # deleting a flight deletes the estimates stored with its results
        with database.transaction() as session:
            kept = set(session.scalars(select(Result.estimates_blob).where(Result.flight_sha256 == shas[1])))
        assert kept and None not in kept and kept <= blob_files(home)
        assert client.delete(f"/flights/{ids[2]}").status_code == 204
        assert not kept & blob_files(home)


def test_a_failure_never_replaces_a_stored_success(registry_home):
    """A flight that succeeded and then fails with the same model and settings (a server shutting down
    under a running job, a lost Dask worker) keeps its stored result and estimates."""
    from sqlalchemy import select

    from learnest.service.jobs.result_cache import store_result
    from learnest.service.storage.tables import Result

    home, ids = registry_home["home"], registry_home["ids"]
    with running_app(home) as client:
        evaluate(client, "quad:1", [ids[1]])       # computed, or answered from the results cache
        database = client.app.state.services.db
        with database.transaction() as session:
            row = session.scalars(select(Result).where(Result.state == "succeeded", Result.flight_id == ids[1],
                                                       Result.estimates_blob.is_not(None))).first()
            before = (row.flight_sha256, row.model_version_id, row.settings_key, row.flight_id, row.entry,
                      row.estimates_blob)
        sha, version_id, key, flight_id, entry, blob = before
        failure = {"flight": "x", "excluded": True, "reason": "failed: worker lost", "mse": {}, "failed": True}
        assert store_result(database, sha, version_id, key, flight_id, failure, "worker lost") is None
        with database.transaction() as session:
            kept = session.scalar(select(Result).where(Result.flight_sha256 == sha, Result.settings_key == key,
                                                       Result.model_version_id == version_id))
            assert (kept.state, kept.entry, kept.estimates_blob, kept.error) == ("succeeded", entry, blob, None)
        assert client.get(f"/flights/{flight_id}").status_code == 200


def test_a_crazyflie_report_page_shows_the_thrust_calibration_and_the_gain_intervals(tmp_path):
    """The page of an evaluation with the Crazyflie prior says what its prior's thrust carried per flight (the
    motors' heating, the flight's thrust gain) and the KNODE's gain with its 95 % interval, the JSON's numbers."""
    from learnest.ingest.formats.nanobench import writer as nanobench
    from learnest.models import crazyflie as cf
    from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie

    paths = []
    drag = {**cf.IDENTIFIED, "k_xy": 3 * cf.IDENTIFIED["k_xy"]}   # something for the residual to learn
    for seed in (0, 1):
        f = simulate_crazyflie(SimulatedFlight(truth=drag, duration_s=15), seed=seed)
        paths.append(tmp_path / f"cf{seed}.csv")
        nanobench.write(paths[-1], f.t + 1.7e9, f.p, f.quat, f.channels["acc_body"] / cf.GRAVITY,
                        motors=f.channels["motors"], vbat=f.channels["vbat"])
    with running_app(tmp_path / "home") as client:
        ids = [upload(client, p).json()["id"] for p in paths]
        trained = client.post("/models", json={"name": "cf", "flight_id": ids[0], "epochs": 20, "system": "crazyflie"})
        assert trained.status_code == 202, trained.text
        assert wait_for_job(client, trained.json()["job_id"])["state"] == "succeeded"
        accepted, report = evaluate(client, "cf:1", [ids[1]], methods=["ukf", "knode-ukf"])
        entry = report["flights"][0]
        page = client.get(f"/evaluations/{accepted['evaluation_id']}/report.html").text
    assert 0.0 < entry["heating_thrust_loss_pct"] < 5.0
    assert "id='motor-heating'" in page and f"{entry['heating_thrust_loss_pct']:.1f} %" in page
    assert "id='thrust-gain'" in page and f"{entry['thrust_gain']:.3f}" in page
    # the headline's interval: over the flight's mocap gaps (the one over time needs three blocks of the errors'
    # own correlation length, which a smooth learned correction can exceed on a 15-s flight)
    low, high = entry["yardsticks"]["mocap_gaps"]["gain_interval_pct"]["knode-ukf_vs_ukf"]
    assert low <= high and f"[{low:+.1f}, {high:+.1f}]" in page


def test_the_report_carries_the_yardsticks_and_the_gap_settings_asked_for(registry_home):
    """GET /evaluations/{id} through its typed response: per flight the three yardsticks (the gaps as asked),
    the headline first; the same numbers as evaluate_flights; gaps that leave no mocap between them are a 422."""
    from learnest.service.storage.registry import load_model_ref
    from learnest.workflows.flights import evaluate_flights

    home = registry_home["home"]
    ids = registry_home["ids"][:2]   # a test above deletes the third flight of this module's registry
    with running_app(home) as client:
        _, report = evaluate(client, "quad:1", ids[1:], gap_s=0.4, gap_every_s=2.0)
        model = load_model_ref("quad:1", settings_for(home))
        direct = json.loads(json.dumps(evaluate_flights(model, stored_flights(home, ids[1:]), FAST_METHODS,
                                                        gap_s=0.4, gap_every_s=2.0)))
        for got, want in zip(report["flights"], direct["flights"]):
            gaps = got["yardsticks"]["mocap_gaps"]
            assert gaps["gap_s"] == 0.4 and gaps["every_s"] == 2.0 and gaps["gaps"] > 0
            assert gaps["rmse_m"] == pytest.approx(want["yardsticks"]["mocap_gaps"]["rmse_m"], rel=1e-9)
            assert got["yardsticks"]["paper_sg"]["mse"] == pytest.approx(got["mse"], rel=1e-12)
        assert report["headline"]["yardstick"] == "mocap_gaps" and report["headline"]["gap_s"] == 0.4
        assert report["headline"]["median_rmse_m"] == pytest.approx(direct["headline"]["median_rmse_m"], rel=1e-9)
        refused = client.post("/evaluations", json={"model": "quad:1", "flights": ids[1:], "gap_s": 1.0,
                                                    "gap_every_s": 0.8})
        assert refused.status_code == 422 and "gap_every_s" in refused.text
        schemas = client.get("/openapi.json").json()["components"]["schemas"]
        assert {"EvaluationReportOut", "FlightScoreOut", "Headline", "MocapGaps", "FastReference",
                "PaperSG"} <= set(schemas)
