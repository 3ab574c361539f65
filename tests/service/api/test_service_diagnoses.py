"""POST /diagnoses runs `learnest diagnose` as a job and registers the repaired model as a new version;
`learnest diagnose --model REF --register NAME` does the same from the CLI (parent: REF's version).

Two small simulated NanoBench flights with a declared accelerometer bias: the diagnosis must find it."""
import contextlib
import io
import json

import numpy as np
import pytest
from utils.service import FAST_METHODS, evaluate, running_app, settings_for, upload, wait_for_job

from learnest.ingest.flight import Flight as CanonicalFlight
from learnest.ingest.sim import RandomWaypoints, SensorModel, simulate, write_flight

BIAS = (0.3, -0.2, 0.25)
EPOCHS = 3
HOSTILE = "<b>cf&"   # uploaded file names are user text: they reach the diagnosis page only made safe


@pytest.fixture(scope="module")
def biased_logs(tmp_path_factory):
    directory = tmp_path_factory.mktemp("diagnoses-logs")
    paths = []
    for seed in (0, 1):
        sim = simulate(RandomWaypoints(count=8, speed=0.8, seed=seed), sensors=SensorModel(bias=BIAS), seed=seed)
        paths.append(write_flight(sim, "nanobench", directory, f"biased{seed}"))
    return paths


def stored_flight(home, flight_id) -> CanonicalFlight:
    from sqlalchemy import select

    from learnest.service.storage.blobs import BlobStore
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import FlightRecord

    database = Database(settings_for(home).url)
    with database.transaction() as session:
        blob = session.scalar(select(FlightRecord.flight_blob).where(FlightRecord.id == flight_id))
    database.dispose()
    return CanonicalFlight.from_bytes(BlobStore(home / "blobs").read_bytes(blob))


def assert_bias_found(report: dict) -> None:
    top = report["effects"][0]
    assert top["id"] == "accel_bias", [e["id"] for e in report["effects"]]
    assert top["params"]["bias_x"] == pytest.approx(BIAS[0], rel=0.2)


def assert_residual_series(series: dict) -> None:
    """The stored accelerometer residual of the held-out flight: its mean is the declared bias before the
    effects (the prior knows no bias) and about zero after; short enough to keep the report small."""
    t, before, after = (np.asarray(series[k]) for k in ("t", "before", "after"))
    assert series["units"] == "m/s²" and series["flight"] == "b_cf_1"
    assert 100 < len(t) <= 1000 and before.shape == after.shape == (len(t), 3) and np.all(np.diff(t) > 0)
    np.testing.assert_allclose(before.mean(axis=0), BIAS, atol=0.05)
    np.testing.assert_allclose(after.mean(axis=0), 0.0, atol=0.05)
    assert np.sqrt(np.mean(after**2)) < 0.5 * np.sqrt(np.mean(before**2))


def assert_diagnosis_page(client, diagnosis_id: int, job_id: int, report: dict) -> None:
    """The report page shows every effect with its units and interval, the alternatives, both plots, the
    before/after numbers, and escapes flight names; the job page links to it and to the registered version."""
    import re

    answer = client.get(f"/diagnoses/{diagnosis_id}/report.html")
    assert answer.status_code == 200 and answer.headers["content-type"].startswith("text/html")
    page = answer.text
    for effect in report["effects"]:
        assert f"<b class='effect-id'>{effect['id']}</b>" in page
        for name, (lo, hi) in effect["ci95"].items():
            unit = effect["units"][name].replace("&", "&amp;")
            assert f"[{lo:.4g}, {hi:.4g}] {unit}" in page, (name, unit)
        for alt in effect["alternatives"]:
            assert f"<b>{alt['id']}</b> with" in page
    assert re.search(r"<img id='residual-series' alt='[^']*' src='data:image/png;base64,", page)
    assert re.search(r"<img id='diagnosis-summary' alt='[^']*' src='data:image/png;base64,", page)
    for method in FAST_METHODS:
        assert f"<b>{report['after'][method]:.4g}</b>" in page
    assert "<b>cf" not in page
    # the split the code made, as the report names it: the page says the same
    fitting = re.search(r"<span id='fitting-flights'>(.*?)</span>", page).group(1)
    scored = re.search(r"<span id='scored-flights'>(.*?)</span>", page).group(1)
    assert re.findall(r">([^<]+)</a>", fitting) == report["fitting_flights"]
    assert re.findall(r">([^<]+)</a>", scored) == report["scored_flights"]
    assert report["scored_flights"] == [p["flight"] for p in report["per_flight"]]
    assert "<a href='/ui/models/cf'>cf:1</a>" in page
    job_page = client.get(f"/ui/jobs/{job_id}").text
    assert f"href='/diagnoses/{diagnosis_id}/report.html'" in job_page
    assert "id='registered-link' href='/ui/models/cf'" in job_page
    assert client.get("/diagnoses/999/report.html").status_code == 404


def stages_while(client, job_id: int, timeout: float = 120.0) -> tuple[list[tuple[str, float]], dict]:
    """(every (stage, progress) GET /jobs/{id} answered while the job ran, in order, the finished job)."""
    import time

    seen: list[tuple[str, float]] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/jobs/{job_id}").json()
        if job["state"] not in ("queued", "running"):
            return seen, job
        if job["state"] == "running" and job["stage"] and (not seen or seen[-1] != (job["stage"], job["progress"])):
            seen.append((job["stage"], job["progress"]))
        time.sleep(0.01)
    raise AssertionError(f"job {job_id} did not finish")


def assert_honest_stages(seen: list[tuple[str, float]], job: dict) -> None:
    """A diagnosis job names more than one kind of stage as it runs (effects fitted, KNODEs trained, flights
    scored), and its progress only grows, within 0..1."""
    from learnest.workflows.diagnosis_stages import stage_kind

    kinds = list(dict.fromkeys(stage_kind(stage) for stage, _ in seen))
    assert len(kinds) > 1, seen
    assert {"fitting effects on accelerometer", "training the KNODE on the repaired prior"} & set(kinds), kinds
    fractions = [fraction for _, fraction in seen]
    assert all(0.0 <= f <= 1.0 for f in fractions) and fractions == sorted(fractions), seen
    assert job["progress"] == 1.0


def test_post_diagnoses_registers_the_repaired_model(tmp_path, biased_logs):
    from learnest.service.storage.registry import load_model_ref
    from learnest.workflows.flights import evaluate_flight

    home = tmp_path / "home"
    with running_app(home, api_key="secret") as client:
        key = {"X-API-Key": "secret"}
        ids = [upload(client, *paths, names=[p.name.replace("biased", HOSTILE) for p in paths], headers=key).json()["id"]
               for paths in biased_logs]
        # the bias repair is right but within the flights' own variability on the held-out UKF score (the
        # interval rule): it is registered only when forced, with the warning stored in the version
        body = {"flights": ids, "register": "cf", "epochs": EPOCHS, "force": True}
        assert client.post("/diagnoses", json=body).status_code == 401
        assert client.post("/diagnoses", json={**body, "flights": []}, headers=key).status_code == 422
        assert client.post("/diagnoses", json={**body, "flights": [999]}, headers=key).status_code == 404
        assert client.post("/diagnoses", json={**body, "model": "nope:1"}, headers=key).status_code == 404
        assert client.get("/diagnoses/999").status_code == 401                   # reads need the key too
        assert client.get("/diagnoses/999", headers=key).status_code == 404

        client.headers.update(key)
        accepted = client.post("/diagnoses", json=body)
        assert accepted.status_code == 202, accepted.text
        seen, job = stages_while(client, accepted.json()["job_id"])
        assert job["state"] == "succeeded", job
        assert_honest_stages(seen, job)
        report = client.get(f"/diagnoses/{accepted.json()['diagnosis_id']}").json()
        assert_bias_found(report)
        assert not report["repair"]["improves"]
        warning = report["registered"].pop("warning")
        assert report["registered"] == {"name": "cf", "version": 1, "parent": None} and "force" in warning
        assert set(report["before"]) == set(report["after"]) == set(FAST_METHODS)
        assert_residual_series(report["residual_series"]["accelerometer"])
        assert_diagnosis_page(client, accepted.json()["diagnosis_id"], accepted.json()["job_id"], report)

        version = client.get("/models/cf/versions/1").json()
        assert version["status"] == "ready" and version["training_flight"]["id"] == ids[0]
        assert version["created_by"] == "api-key"       # the diagnosis' token, on the version it registered
        assert version["hyperparameters"]["epochs"] == EPOCHS and version["code_version"]["package"] == "learnest"
        assert version["prior"]["measurement_effects"]["bias_x"] == pytest.approx(BIAS[0], rel=0.2)
        assert "accel_bias" in version["prior"]["effects"]

        model = load_model_ref("cf:1", settings_for(home))
        assert model.meta["measurement_effects"] == version["prior"]["measurement_effects"]
        assert "accel_bias" in model.meta["effects"]
        # evaluating with it applies the correction: the job's numbers are evaluate_flight's
        _, evaluation = evaluate(client, "cf:1", [ids[1]])
        direct = evaluate_flight(model, stored_flight(home, ids[1]), FAST_METHODS)["results"]
        assert evaluation["flights"][0]["mse"]["knode-ukf"] == pytest.approx(direct["knode-ukf"]["mse"], rel=1e-9)
        model.meta["measurement_effects"] = {}
        uncorrected = evaluate_flight(model, stored_flight(home, ids[1]), ["knode-ukf"])["results"]
        assert uncorrected["knode-ukf"]["mse"] != pytest.approx(direct["knode-ukf"]["mse"], rel=1e-6)


def test_cli_diagnose_registers_a_child_version(tmp_path, biased_logs, monkeypatch):
    from learnest.service.cli import main
    from learnest.service.storage.registry import load_model_ref

    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    files = [str(p) for paths in biased_logs for p in paths]

    log = io.StringIO()   # stderr piped into a file: no bar, one plain line per kind of stage

    def run(*argv) -> dict:
        buffer = io.StringIO()
        with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(log):
            assert main([*argv, "--json"]) == 0
        return json.loads(buffer.getvalue())

    assert run("train", files[0], "--name", "cf", "--epochs", "2")["ref"] == "cf:1"
    log.seek(0)
    log.truncate()
    report = run("diagnose", *files, "--model", "cf:1", "--register", "cf", "--epochs", str(EPOCHS), "--force")
    assert_bias_found(report)
    lines = [line for line in log.getvalue().splitlines() if line.startswith("learnest: diagnosing: ")]
    assert "\r" not in log.getvalue()
    stages = [line.removeprefix("learnest: diagnosing: ").rsplit(" (", 1)[0] for line in lines]
    # the model is given: no KNODE is trained on the unrepaired prior
    assert stages == [f"reading {len(files)} file(s)", "fitting effects on accelerometer", "pre-training observer",
                      "fitting effects on translational dynamics", "pre-training observer",
                      "training the KNODE on the repaired prior",
                      "scoring before/after", "done"], lines
    percents = [int(line.rsplit("(", 1)[1].split(" %")[0]) for line in lines[:-1]]
    assert percents == sorted(percents) and 0 <= percents[0] and percents[-1] <= 100, lines
    assert report["registered"].pop("warning").startswith("registered with --force")
    assert report["registered"] == {"name": "cf", "version": 2, "parent": "cf:1"}
    # the kinematic prior's split: the first flight fits, the others are scored; the CLI's text says so second
    from learnest.service.cli import diagnosis_lead
    assert len(report["fitting_flights"]) == 1
    assert report["scored_flights"] == [p["flight"] for p in report["per_flight"]] and report["scored_flights"]
    lead = diagnosis_lead(report)
    assert lead[0].startswith("Found accel_bias")
    assert lead[1] == (f"split: fitted on {report['fitting_flights'][0]}; scored on "
                       f"{', '.join(report['scored_flights'])} ({report['split']})")
    model = load_model_ref("cf:2")
    assert "accel_bias" in model.meta["effects"] and model.meta["measurement_effects"]
    with running_app(tmp_path / "home") as client:
        versions = client.get("/models/cf").json()["versions"]
        assert [(v["version"], v["parent"]) for v in versions] == [(1, None), (2, "cf:1")]
        assert versions[0]["training_flight"] == versions[1]["training_flight"]   # the same stored flight
        assert client.get("/flights").json()["total"] == 1


def test_post_diagnoses_with_the_crazyflie_prior(tmp_path):
    """`"system": "crazyflie"`: the input-driven prior is diagnosed (a battery exponent the prior gets
    wrong), the report names its prior; a flight without motor PWM fails with the message saying so."""
    from learnest.ingest.formats.nanobench import writer as nanobench
    from learnest.models import crazyflie as cf
    from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie

    truth = {**cf.IDENTIFIED, "gamma": 1.2}
    paths = []
    for seed in (0, 1, 2):
        f = simulate_crazyflie(SimulatedFlight(truth=truth, duration_s=20), seed=seed)
        paths.append(tmp_path / f"cf{seed}.csv")
        motors = None if seed == 2 else f.channels["motors"]
        nanobench.write(paths[-1], f.t + 1.7e9, f.p, f.quat, f.channels["acc_body"] / cf.GRAVITY, motors=motors,
                        vbat=f.channels["vbat"])
    with running_app(tmp_path / "home") as client:
        ids = [upload(client, p).json()["id"] for p in paths]
        body = {"flights": ids[:2], "methods": ["ukf"], "epochs": 1, "system": "crazyflie"}
        assert client.post("/diagnoses", json={**body, "system": "robot"}).status_code == 422
        accepted = client.post("/diagnoses", json=body)
        assert accepted.status_code == 202, accepted.text
        assert wait_for_job(client, accepted.json()["job_id"])["state"] == "succeeded"
        report = client.get(f"/diagnoses/{accepted.json()['diagnosis_id']}").json()
        assert report["system"] == "crazyflie" and report["prior"]["params"]["gamma"] == cf.IDENTIFIED["gamma"]
        assert report["effects"][0]["id"] == "battery_thrust"
        assert report["effects"][0]["nominal"] == {"gamma": cf.IDENTIFIED["gamma"]}
        # the held-out flight's specific force from the inputs: the wrong exponent leaves a residual that the
        # fitted one removes, the same numbers as the report's specific_force_rmse
        series = report["residual_series"]["specific force"]
        rms = {k: float(np.sqrt(np.mean(np.square(series[k])))) for k in ("before", "after")}
        assert rms["after"] < 0.7 * rms["before"]
        assert rms["before"] == pytest.approx(report["before"]["specific_force_rmse"], rel=0.1)
        page = client.get(f"/diagnoses/{accepted.json()['diagnosis_id']}/report.html").text
        assert "<b class='effect-id'>battery_thrust</b>" in page and "id='residual-series'" in page
        assert "id='candidates'" in page and "gamma = " in page

        failing = client.post("/diagnoses", json={**body, "flights": [ids[2], ids[0]]})
        job = wait_for_job(client, failing.json()["job_id"])
        assert job["state"] == "failed" and "motor PWM" in json.dumps(job)
