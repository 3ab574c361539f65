"""Estimators and evaluation on Flights: what `learnest.ukf`, `learnest.mhe` and `learnest.evaluate` run.

The estimators themselves (`learnest.estimators`) work on arrays; this layer supplies what a Flight
implies: its measurements y = [p, a_meas] and the estimators' bundle (`estimators.prepared.prepare`: the
model on the flight's grid, its noise and the first state).
"""
from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import numpy as np

from learnest.errors import InvalidInput, NumericalWarning
from learnest.estimators.estimates import FlightEstimates
from learnest.estimators.evaluation_settings import EvaluationSettings, Noise
from learnest.estimators.headline import ReportHeadline
from learnest.estimators.mhe import MHE
from learnest.estimators.prepared import FLIGHT_SYSTEMS, PreparedFlight, prepare
from learnest.estimators.results import FilterResult, MHEResult
from learnest.estimators.ukf import run_ukf
from learnest.ingest.flight import Flight
from learnest.models.knode import HybridModel
from learnest.models.presets import EVALUATION_METHODS, GAP_EVERY_S, GAP_S, MHE_HORIZON

from .flights import score_flights


def _checked(model: HybridModel, flight: Flight, noise: str) -> PreparedFlight:
    if not isinstance(flight, Flight):
        raise InvalidInput(f"expected a Flight (learnest.read_flights), got {type(flight).__name__}")
    if model.system.name not in FLIGHT_SYSTEMS:
        raise InvalidInput(f"a {model.system.name!r} model cannot run on a flight; flights need one of "
                           f"{', '.join(FLIGHT_SYSTEMS)}")
    return prepare(model, flight, noise=noise)   # a model a diagnosis repaired sees the flight as evaluate does


def ukf(model: HybridModel, flight: Flight, alpha: float = 1e-3, noise: str = "identified") -> FilterResult:
    """Unscented Kalman filter of one flight with ``model`` (a KNODE's ``model_`` or a prior).

    Parameters
    ----------
    model : HybridModel
        Discrete 9-state flight model ("quadrotor" or "crazyflie"), x = [p (m), v (m/s), a (m/s²)].
    flight : Flight
        Measurements y = [p, a_meas] on the flight's grid.
    alpha : float
        Merwe sigma-point spread.
    noise : {"identified", "paper"}
        The model's own noise, identified on its training flights (the system's fixed noise for a model
        that never had it identified), or the system's fixed noise (`estimators.prepared.noise_models`).

    Returns
    -------
    FilterResult
        ``t`` (T,) s, ``means`` (T, 9), ``covariances`` (T, 9, 9), ``innovations`` (T, 6) in the units of
        y = [p (m), a_meas (m/s²)], ``log_likelihoods`` (T,) nats.  x0 is `initial_state` (p[0], mean
        velocity over the first 5 steps, a_meas[0]).

    Raises
    ------
    InvalidInput
        If ``flight`` is not a Flight or ``model`` is not a quadrotor model.

    Examples
    --------
    >>> import learnest as le
    >>> flights = le.read_flights(["sample_logs/circle_rep1.csv", "sample_logs/circle_rep2.csv"])
    >>> knode = le.KNODE(epochs=20).fit(flights[0])
    >>> post = le.ukf(knode.model_, flights[1])
    >>> post.means.shape == (len(flights[1].t), 9)
    True
    """
    prepared = _checked(model, flight, noise)
    result = run_ukf(prepared.params, prepared.y, prepared.u, alpha=alpha)
    return result._replace(t=np.asarray(flight.t, dtype=float))


def mhe(model: HybridModel, flight: Flight, horizon: int = MHE_HORIZON, noise: str = "identified") -> MHEResult:
    """Moving horizon estimate (eq. 2) of one flight with ``model``.

    Parameters
    ----------
    model : HybridModel
        Discrete 9-state flight model ("quadrotor" or "crazyflie"), x = [p (m), v (m/s), a (m/s²)].
    flight : Flight
        Measurements y = [p, a_meas] on the flight's grid.
    horizon : int
        Window length N, samples.
    noise : {"identified", "paper"}
        As `ukf`.

    Returns
    -------
    MHEResult
        ``t`` (T,) s, ``means`` (T, 9), ``covariances`` (T, 9, 9), ``solver_failures``.  x0 as in `ukf`.

    Raises
    ------
    InvalidInput
        If ``flight`` is not a Flight, ``model`` is not a quadrotor model, or ``horizon`` is not a whole
        number of at least 1 (`models.presets.check_mhe_options`).

    Warns
    -----
    NumericalWarning
        If the NLP solver failed on some windows.

    Examples
    --------
    >>> import learnest as le
    >>> flight = le.read_flights(["sample_logs/circle_rep2.csv"])[0]
    >>> prior = le.HybridModel(le.make_system("quadrotor"))
    >>> result = le.mhe(prior, flight, horizon=20)
    >>> result.covariances.shape[1:]
    (9, 9)
    """
    prepared = _checked(model, flight, noise)
    estimator = MHE(prepared.params, horizon=horizon)
    result = estimator.run(prepared.y, prepared.u, covariances=True)
    if result.solver_failures:
        warnings.warn(f"{flight.name}: the MHE solver failed on {result.solver_failures} of "
                      f"{estimator.stats['solves']} windows; those estimates are the solver's last iterate",
                      NumericalWarning, stacklevel=2)
    return result._replace(t=np.asarray(flight.t, dtype=float))


def evaluate(model: HybridModel, flights: Sequence[Flight], methods: Sequence[str] = EVALUATION_METHODS,
             horizon: int = MHE_HORIZON, include_bad: bool = False,
             progress: Callable[[dict], None] | None = None,
             on_estimates: Callable[[int, FlightEstimates], None] | None = None,
             gap_s: float = GAP_S, gap_every_s: float = GAP_EVERY_S, noise: Noise = "identified") -> dict:
    """Score the estimators on flights against Savitzky–Golay references of their mocap position.

    Parameters
    ----------
    model : HybridModel
        The KNODE (its prior runs the "ukf"/"mhe" rows).  Its own training flight is never scored.
    flights : sequence of Flight
        Flights to score (each gets an entry, excluded ones with the reason).
    methods : sequence of str
        Any of ``"ukf", "mhe", "knode-ukf", "knode-mhe"``, and ``"onboard"``: the vehicle's own estimate,
        scored on the fast reference where the log carries it.
    horizon : int
        MHE window N, samples.
    include_bad : bool
        Also score flights that fail the quality checks.
    progress : callable, optional
        Called with each flight's entry as it is done.
    on_estimates : callable, optional
        Called as ``on_estimates(index, FlightEstimates)`` with the per-step estimates of every method on
        each scored flight (``index`` into ``flights``); `learnest.estimators.export.write_estimates`
        writes them as CSV, Parquet or MCAP, `FlightEstimates.to_frame` gives the tidy table.
    gap_s, gap_every_s : float
        The mocap-gap yardstick: the mocap position is hidden from the estimators for ``gap_s`` s every
        ``gap_every_s`` s after the first 5 s (`learnest.estimators.yardsticks`); ``gap_s = 0`` turns it off.
    noise : {"identified", "paper"}
        Each model (the KNODE and its prior) with its own noise identified on the training flights (the
        system's fixed noise where the model has none), or both with the system's fixed noise.

    Returns
    -------
    dict
        ``noise`` {method: "identified" | "paper"}: what each method ran with; ``flights``: per flight ``mse``
        {method: MSE over [p, v, a] in SI units²}, ``groups`` (per p, v,
        a), ``ms_per_step``, ``excluded`` and ``reason``; ``median`` {method: MSE}; ``units`` of these;
        ``improvement_pct`` {"knode-ukf_vs_ukf": %, ...}; ``flights_scored``; ``model`` (the model's
        meta name, None for an unregistered model).  Per flight ``yardsticks``: ``mocap_gaps`` (``rmse_m``
        {method: m}, ``gain_pct``, ``gain_interval_pct``, ``gap_s``, ``every_s``, ``gaps``), ``fast_reference``
        (``velocity_rmse_m_s`` {method: m/s}, ``window_s``) and ``paper_sg`` (``mse``); ``headline``: the
        KNODE's median gap gain, the flights it is better on and worse beyond their interval on (a
        `ReportHeadline`: the dict, printed as a sentence).

    Raises
    ------
    InvalidInput
        If a method name is unknown, or a setting is out of its bounds (`EvaluationSettings`).

    Examples
    --------
    >>> import learnest as le
    >>> flights = le.read_flights(["sample_logs/circle_rep1.csv", "sample_logs/circle_rep2.csv"])
    >>> knode = le.KNODE(epochs=20).fit(flights[0])
    >>> report = le.evaluate(knode.model_, flights, methods=("ukf", "knode-ukf"))
    >>> report["flights_scored"]      # flights[0] is the training flight: never scored
    1
    """
    # the settings' type parses a comma-separated string as it parses a list of names
    settings = EvaluationSettings((methods,) if isinstance(methods, str) else tuple(methods), horizon, include_bad,
                                  gap_s=gap_s, gap_every_s=gap_every_s, noise=noise)
    told = None if progress is None else (lambda score: progress(score.to_dict()))
    report = score_flights(model, list(flights), settings, progress=told, on_estimates=on_estimates).to_dict()
    if report.get("headline") is not None:   # prints as its sentence; still the same dict
        report["headline"] = ReportHeadline(report["headline"])
    return report
