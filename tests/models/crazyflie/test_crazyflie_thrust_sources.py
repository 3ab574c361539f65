"""The Crazyflie diagnosis on what a log carries of the thrust (motor PWM + battery, rotor speed, thrust in N),
with physically true names and values: a thrust gain unless the mass is known, a flag for a vehicle that is
not the prior's, no parameter claimed at a physical bound, cancelling pairs never both claimed, a repair
registered only when it helps held-out flights.  Simulated flights: `models.crazyflie.simulate_crazyflie` (the
truth)."""
from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

import learnest as le
from learnest.ingest import read_flights
from learnest.ingest.formats.nanobench import writer as nanobench
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.crazyflie.thrust_map import fit_bench_map
from learnest.models.knode import HybridModel
from learnest.models.systems import make_system
from learnest.service.cli import main
from learnest.workflows.diagnosis import diagnose_crazyflie, format_diagnosis
from learnest.workflows.thrust_map import bench_thrust_map_report

M0 = 0.016
BASE = {**cf.IDENTIFIED, "m_kg": M0, "kappa_th": 0.0}
DATA = Path(__file__).resolve().parents[4] / "shared" / "data"
LOG182 = str(DATA / "crazyswarm2-tools" / "log182")
NANOBENCH = DATA / "nanobench"


def _flights(truth, source, n=3, controller=BASE, **settings):
    return [simulate_crazyflie(SimulatedFlight(truth=truth, controller=controller, duration_s=20,
                                               thrust_source=source, **settings), seed=s) for s in range(n)]


def _contract(report):
    """Every effect entry carries the contract's keys, and nothing is claimed at a bound."""
    assert report["thrust_source"] in cf.THRUST_SOURCES
    assert set(report["vehicle_fits_prior"]) == {"ok", "thrust_gain", "message"}
    for effect in report["effects"]:
        assert set(effect["identified"]) == set(effect["params"]) == set(effect["at_bound"])
        for name, ok in effect["identified"].items():
            assert not (ok and effect["at_bound"][name]), (effect["id"], name)
            assert effect["claimed"][name] == ok


def test_thrust_in_newtons_gives_a_payload_as_a_mass_in_kg():
    prior = cf.prior_for("thrust_n", M0, BASE)
    report = diagnose_crazyflie(_flights({**BASE, "m_kg": 1.2 * M0}, "thrust_n"), methods=(), prior=prior)
    _contract(report)
    top = report["effects"][0]
    assert report["thrust_source"] == "thrust_n" and top["id"] == "mass" and top["units"] == {"m_kg": "kg"}
    assert top["params"]["m_kg"] == pytest.approx(1.2 * M0, rel=0.05)        # measured: +0.5 %
    assert top["identified"] == {"m_kg": True}
    assert report["after"]["specific_force_rmse"] < report["before"]["specific_force_rmse"]


def test_a_thrust_command_the_accelerometer_contradicts_is_a_command_scale_not_a_mass():
    """A vehicle whose thrust per PWM is 1.6x what its controller's map assumes logs a command 1/1.6 of the
    thrust it makes: read as exact, the mass would be M0/1.6 against the prior's M0.  Position and
    accelerometer measure only thrust made / mass, so the report gives the thrust made over the command
    (1.6, with the prior's mass) and the implied mass, and claims no mass."""
    prior = cf.prior_for("thrust_n", M0, BASE)
    report = diagnose_crazyflie(_flights({**BASE, "m_kg": M0 / 1.6}, "thrust_n"), methods=(), prior=prior)
    _contract(report)
    assert "mass" not in {e["id"] for e in report["effects"]}
    scale = report["effects"][0]
    assert scale["id"] == "thrust_gain" and scale["params"]["gain"] == pytest.approx(1.6, rel=0.05)
    assert scale["implied_mass_kg"] == pytest.approx(M0 / 1.6, rel=0.05)
    assert "No mass is claimed" in scale["note"] and "under-promises" in scale["note"]
    assert not report["vehicle_fits_prior"]["ok"]


def test_a_flight_with_only_thrust_in_newtons_picks_the_thrust_prior_and_its_declared_mass():
    flights = _flights({**BASE, "m_kg": 1.2 * M0}, "thrust_n", n=2)
    assert "motors" not in flights[0].channels and "thrust_si" in flights[0].channels
    report = diagnose_crazyflie(flights, methods=(), mass_kg=M0)
    assert report["thrust_source"] == "thrust_n" and report["declared_mass_kg"] == M0
    assert report["prior"]["params"]["m_kg"] == M0 and report["prior"]["params"]["thrust_source"] == "thrust_n"
    assert report["effects"][0]["id"] == "mass"
    assert report["effects"][0]["params"]["m_kg"] == pytest.approx(1.2 * M0, rel=0.05)


def test_rotor_speed_without_a_declared_mass_gives_a_thrust_gain_and_no_battery_effect():
    prior = cf.prior_for("rpm", M0, {**BASE, "tau_s": 0.0})
    truth = {**BASE, "m_kg": 1.2 * M0, "tau_s": 0.0, "gamma": 1.5}    # the battery acts before the rotor speed
    report = diagnose_crazyflie(_flights(truth, "rpm", controller={**BASE, "tau_s": 0.0}), methods=(), prior=prior)
    _contract(report)
    assert report["thrust_source"] == "rpm"
    assert [e["id"] for e in report["effects"]][:1] == ["thrust_gain"]
    assert report["effects"][0]["params"]["gain"] == pytest.approx(1 / 1.2, rel=0.05)
    assert "battery_thrust" not in {c["id"] for c in report["candidates"]}


def test_a_vehicle_with_1_8_times_the_thrust_per_pwm_does_not_fit_the_prior():
    report = diagnose_crazyflie(_flights({**BASE, "m_kg": M0 / 1.8}, "pwm", n=2), methods=(), prior=BASE)
    fits = report["vehicle_fits_prior"]
    assert not fits["ok"] and fits["thrust_gain"] == pytest.approx(1.8, rel=0.05)
    assert "thrust-map" in fits["message"] and "bench" in fits["message"]
    assert "mass" not in {e["id"] for e in report["effects"]}       # a gain, not a mass in kg
    _contract(report)


def test_a_lag_beyond_the_physical_bound_is_not_claimed():
    # a 0.2-s "lag" is no 7-mm motor's: the fit stops at the 0.1-s bound and is reported, not claimed
    truth, prior = {**BASE, "tau_s": 0.2}, {**BASE, "tau_s": 0.0}
    report = diagnose_crazyflie(_flights(truth, "pwm", n=2, controller=prior), methods=(), prior=prior)
    _contract(report)
    lag = next(e for e in report["effects"] if e["id"] == "motor_lag")
    assert lag["at_bound"] == {"tau_s": True} and lag["identified"] == {"tau_s": False}
    assert lag["params"]["tau_s"] == pytest.approx(cf.BOUNDS["tau_s"][1], abs=1e-3)
    assert "not claimed" in format_diagnosis(report)


def test_an_accelerometer_bias_and_a_tilt_are_never_both_claimed():
    report = diagnose_crazyflie(_flights(BASE, "pwm", accel_bias=(0.25, -0.15, 0.0)), methods=(), prior=BASE)
    claimed = {e["id"]: e["params"] for e in report["effects"] if any(e["identified"].values())}
    assert not {"accel_bias", "accel_misalignment"} <= set(claimed)
    assert claimed["accel_bias"]["bias_x"] == pytest.approx(0.25, rel=0.2)
    assert claimed["accel_bias"]["bias_y"] == pytest.approx(-0.15, rel=0.2)


def test_the_notebook_diagnoses_with_a_crazyflie_model_and_raises_learnest_errors():
    flights = _flights(BASE, "pwm", n=2)
    model = HybridModel(make_system("crazyflie", prior_params=dict(BASE)), "prior")
    report = le.diagnose(flights, model=model, methods=("ukf",))       # the model's own prior: no system given
    assert report["system"] == "crazyflie" and set(report["before"]) == {"specific_force_rmse", "ukf"}
    flights[0].channels.pop("motors")
    with pytest.raises(le.LearnestError, match="motor PWM"):
        le.diagnose(flights, system="crazyflie", methods=())
    with pytest.raises(le.LearnestError, match="crazyflie"):
        le.diagnose(_flights(BASE, "pwm", n=1), model=model, system="quadrotor", methods=())


def test_a_long_hover_with_a_slow_accelerometer_is_diagnosed_from_one_flight():
    # an accelerometer logged at 20 Hz over the radio and resampled to 100 Hz: 4 of 5 rows interpolated
    flight = simulate_crazyflie(SimulatedFlight(truth=BASE, controller=BASE, duration_s=51, speeds=(0.0,)))
    acc = flight.channels["acc_body"]
    measured = np.arange(0, len(acc), 5)
    flight.channels["acc_body"] = np.column_stack([np.interp(np.arange(len(acc)), measured, a[measured])
                                                   for a in acc.T])
    report = diagnose_crazyflie([flight], methods=(), prior=BASE)
    assert report["split"].startswith("one flight") and len(report["per_flight"]) == 1
    _contract(report)


def test_a_bench_calibration_csv_gives_the_gain_against_the_priors_map(tmp_path):
    pwm = np.linspace(8000, 62000, 12)
    volts = np.linspace(4.1, 3.5, 12)
    thrust = 1.25 * (cf.FOERSTER_A2 * pwm**2 + cf.FOERSTER_A1 * pwm + cf.FOERSTER_A0) * (volts / cf.V_REF) ** 1.3
    bench = fit_bench_map("pwm", pwm, thrust, volts)
    assert bench.gamma == pytest.approx(1.3, rel=0.02) and bench.rmse_n < 1e-6
    path = tmp_path / "bench.csv"
    path.write_text("pwm,thrust_g,vbat\n" + "".join(f"{p:.0f},{1e3 * t / cf.GRAVITY:.6f},{v:.4f}\n"
                                                    for p, t, v in zip(pwm, thrust, volts)))
    report = bench_thrust_map_report(path, mass_kg=0.030)
    ratio = np.sum(thrust) / np.sum((cf.FOERSTER_A2 * pwm**2 + cf.FOERSTER_A1 * pwm + cf.FOERSTER_A0)
                                    * (volts / cf.V_REF))
    assert report["gain_vs_prior"] == pytest.approx(ratio, rel=1e-3)
    assert report["prior_params"]["m_kg"] == pytest.approx(0.030 / ratio, rel=1e-3)
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        assert main(["thrust-map", "--bench", str(path), "--json"]) == 0
    assert json.loads(buffer.getvalue())["kind"] == "pwm"
    (tmp_path / "bad.csv").write_text("pwm,force\n1,2\n")
    assert main(["thrust-map", "--bench", str(tmp_path / "bad.csv")]) == 2


def test_a_repair_that_does_not_help_held_out_flights_is_not_registered(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    paths = []
    # the fitting flight carries an 8 % payload the held-out one does not: a repair for it hurts held-out data
    loaded = simulate_crazyflie(SimulatedFlight(truth={**cf.IDENTIFIED, "m_kg": 1.08 * cf.IDENTIFIED["m_kg"]},
                                                duration_s=20), seed=0)
    plain = simulate_crazyflie(SimulatedFlight(duration_s=20), seed=1)
    for i, f in enumerate([loaded, plain]):
        paths.append(str(tmp_path / f"f{i}.csv"))
        nanobench.write(paths[-1], f.t + 1.7e9, f.p, f.quat, f.channels["acc_body"] / cf.GRAVITY,
                        motors=f.channels["motors"], vbat=f.channels["vbat"])
    args = ["diagnose", *paths, "--system", "crazyflie", "--methods", "ukf", "--epochs", "1", "--register", "cf"]
    assert main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert "registered" not in report and "does not improve" in report["not_registered"]
    gain = next(e for e in report["effects"] if e["id"] == "thrust_gain")
    assert gain["params"]["gain"] == pytest.approx(1 / 1.08, rel=0.02)        # found on the fitting flight
    assert gain["identified"] == {"gain": False} and "does not transfer" in gain["held_out"]
    assert main([*args, "--force", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["registered"]["version"] == 1 and "--force" in report["registered"]["warning"]
    assert main(["models", "show", "cf:1"]) == 0
    assert "prior crazyflie" in capsys.readouterr().out


@pytest.mark.data
def test_nanobench_gives_the_thrust_gain_with_an_interval_and_the_battery_exponent_only_if_determined():
    flights = read_flights(sorted(str(p) for p in NANOBENCH.glob("B2_circle_fast_rep*.csv")))
    report = diagnose_crazyflie(flights, methods=())
    _contract(report)
    fit = report["thrust_map_fit"]
    # the prior was identified on this vehicle: its map holds to a few %, with an interval around the value
    assert fit["gain_ci95"][0] <= fit["gain"] <= fit["gain_ci95"][1] and abs(fit["gain"] - 1) < 0.1
    assert not any(fit["at_bound"].values()) and report["vehicle_fits_prior"]["ok"]
    if fit["gamma_identified"]:     # with the map's shape refitted beside it
        assert fit["gamma_ci95"][0] <= fit["gamma"] <= fit["gamma_ci95"][1]
        assert cf.BOUNDS["gamma"][0] < fit["gamma"] < cf.BOUNDS["gamma"][1]
    else:                           # on circles the PWM follows the battery: the map's shape can stand in for gamma
        assert fit["gamma"] is None and fit["gamma_ci95"] is None and fit["gamma_reason"]


@pytest.mark.data
def test_crazyswarm2_logs_carry_thrust_in_newtons_and_the_declared_mass():
    (flight,) = read_flights([LOG182])
    assert flight.meta["mass_kg"] == pytest.approx(0.032)
    assert np.asarray(flight.channels["thrust_si"]).shape == (len(flight.t), 1)
    report = diagnose_crazyflie([flight], methods=())
    _contract(report)
    assert report["thrust_source"] == "thrust_n" and report["declared_mass_kg"] == pytest.approx(0.032)
    assert report["prior"]["params"]["m_kg"] == pytest.approx(0.032)
    # The logs start in the air with a commanded ~0.5 N while the accelerometer reads 1 g: were the command the
    # thrust made, the mass would be ~51 g against the declared 32 g.  Position and accelerometer measure only
    # thrust made / mass, so no mass is claimed: the thrust made is ~0.62 of the command, with the declared mass.
    assert "mass" not in {e["id"] for e in report["effects"]}
    scale = next(e for e in report["effects"] if e["id"] == "thrust_gain")
    assert 0.5 < scale["params"]["gain"] < 0.7 and scale["implied_mass_kg"] > 0.045
    assert scale["params"]["gain"] == pytest.approx(0.032 / scale["implied_mass_kg"], rel=1e-6)
    text = format_diagnosis(report)
    assert "thrust made is ×0.6" in text and "No mass is claimed" in text
    assert not report["vehicle_fits_prior"]["ok"]


def test_dimensionless_parameters_print_without_a_unit():
    """gamma and kappa_th are dimensionless (unit "1"): "gamma = 1.155", never "gamma = 1.155 1"; a
    parameter with a unit keeps it."""
    from learnest.models.effects import crazyflie_effects
    from learnest.workflows.diagnosis_format import _unit

    battery = next(e for e in crazyflie_effects() if e.id == "battery_thrust")
    assert battery.equation({"gamma": 1.155}) == "battery_thrust: gamma = 1.155"
    lag = next(e for e in crazyflie_effects() if e.id == "motor_lag")
    assert lag.equation({"tau_s": 0.03}) == "motor_lag: tau_s = 0.03 s"
    assert _unit("1") == "" and _unit(None) == "" and _unit("kg") == "kg"
