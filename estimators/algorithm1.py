"""Algorithm 1 of the paper, one implementation: pre-training observer -> state observations ζ -> KNODE training
(`models.training`), on one record or on several flights of one vehicle, the observer a constructor argument.

`Algorithm1.fit` trains on one record with time blocks of it held out (the paper's protocol: the cartpole and
robot of Table I, one flight); `Algorithm1.fit_flights` trains on real flights: one flight is the paper's
protocol, several train one residual on one pooled loss with whole flights held out
(`models.pooled_training.train_knode_pooled`, why there); `Algorithm1.fit_states` is the training phase alone, on
states already observed (every state measured, as in Table I's "full state" rows).  The workflows train only
through this class (an import contract in pyproject.toml keeps them off the trainers).

The network learns whatever the observer's estimates of the unmeasured states contain, artefacts included.
Ways to make those estimates better (the evidence for each is on the results page `docs/results/table1.md`,
"How the KNODE is trained"):

* ``observer="smoother"``: a fixed-interval smoother instead of a filter where the paper's observer is a
  filter (the robot's precursory UKF gets its unscented RTS pass; the cartpole's observer is an unscented
  RTS smoother with the prior instead of the model-free kinematic KF + RTS);
* ``rounds > 0``: after training, smooth the record again with the learned model (`smoother.run_urts`) and
  train on those estimates; stop when the learned model explains the measurements no better than the
  previous round's (mean squared forward innovation, whitened by R: it needs no ground truth);
* ``observer="joint"``: the filter's estimates only start a joint fit of the record's states and Δθ
  (`estimators.joint_training.train_jointly`, the full-record MHE with the network free), so the states the
  network learns from must also follow the learned model.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.ingest.profile import flight_profile
from learnest.models.ensemble import mean_residual
from learnest.models.inputs import training_meta
from learnest.models.knode import HybridModel
from learnest.models.pooled_training import TrainingRecord, train_members_pooled
from learnest.models.presets import TrainingConfig
from learnest.models.systems import System
from learnest.models.training import NOT_LEARNED as NOT_LEARNED  # re-exported: the workflows read training here
from learnest.models.training import TrainingResult, attitude_blind, train_knode

from .flight_training import check_one_vehicle, default_validation, flight_inputs, flight_lineage, pooled_profile
from .observers import Observer, observe_robot, pretraining_observer
from .prepared import model_params
from .smoother import run_urts

OBSERVER_KINDS = ("filter", "smoother", "joint")


def first_observation(system: System, y: np.ndarray, u: np.ndarray, dt: float, observer: str) -> np.ndarray:
    """ζ (T, n) of the chosen observer before any learning: ``"filter"`` is `pretraining_observer` (the
    paper's), ``"smoother"`` the smoothing variant described in the module docstring; ``"joint"`` starts from
    the filter's.

    Raises
    ------
    InvalidInput
        If ``observer`` is not one of ``OBSERVER_KINDS``.
    """
    if observer not in OBSERVER_KINDS:
        raise InvalidInput(f"observer must be one of {', '.join(OBSERVER_KINDS)}, got {observer!r}")
    if observer in ("filter", "joint") or system.name not in ("cartpole", "robot"):
        return pretraining_observer(system, y, u, dt)   # quadrotor/crazyflie: already KF + RTS
    if system.name == "robot":
        return observe_robot(system, y, u, dt, smooth=True)
    from learnest.models.knode import HybridModel

    kinematic = pretraining_observer(system, y, u, dt)  # its first state starts the model's smoother
    return run_urts(model_params(HybridModel(system, "prior"), kinematic[0], dt), y, u).means


def _misfit(innovations: np.ndarray, R: np.ndarray) -> float:
    """Mean squared forward innovation per measurement, in units of its noise variance (1 = noise)."""
    return float(np.mean(innovations**2 / np.diag(R)))


@dataclass(frozen=True)
class Algorithm1:
    """Algorithm 1 with a chosen pre-training observer and observer -> train rounds.

    Parameters
    ----------
    observer : {"filter", "smoother", "joint"} or callable
        The pre-training observer (`first_observation`; "filter" is the paper's), or an observer object
        ``observer(system, y, u, dt) -> ζ (T, n)``.  "joint" starts `estimators.joint_training.train_jointly`
        from the filter's estimates instead of training on them (one record only).
    config : TrainingConfig
        Training settings, the same in every round (each round trains from the config's seed).
    rounds : int
        Extra observer -> train rounds at most (one record only); 0 is Algorithm 1 as printed (ignored with
        "joint").

    Raises
    ------
    InvalidInput
        On an unknown observer kind or ``rounds < 0``.
    """

    observer: str | Observer = "filter"
    config: TrainingConfig = field(default_factory=TrainingConfig)
    rounds: int = 0

    def __post_init__(self) -> None:
        if self.rounds < 0:
            raise InvalidInput(f"rounds must be at least 0, got {self.rounds}")
        if not (self.observer in OBSERVER_KINDS if isinstance(self.observer, str) else callable(self.observer)):
            got = repr(self.observer) if isinstance(self.observer, str) else type(self.observer).__name__
            raise InvalidInput(f"observer must be one of {', '.join(OBSERVER_KINDS)} or a callable, got {got}")

    @property
    def kind(self) -> str:
        """The observer's name: its kind, or the callable's ``__name__``."""
        return self.observer if isinstance(self.observer, str) else getattr(self.observer, "__name__", "observer")

    def observe(self, system: System, y: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """ζ (T, n) of this observer on one record: y (T, m), u (T, p), dt s."""
        if isinstance(self.observer, str):
            return first_observation(system, y, u, dt, self.observer)
        return np.asarray(self.observer(system, y, u, dt), dtype=float)

    def observe_flight(self, flight: Flight, system: str) -> tuple[System, np.ndarray, np.ndarray, float | None]:
        """One flight's Algorithm-1 data with the named prior: (its system on the flight's grid, ζ (T, n) of this
        observer, u (T, p) with the flight's thrust gain, that gain or None: `estimators.flight_training`)."""
        prior, u, gain = flight_inputs(flight, system)
        return prior, self.observe(prior, flight.measurements(), u, prior.dt), u, gain

    def fit(self, system: System, y: ArrayLike, u: ArrayLike, dt: float,
            progress: Callable[[int, float], None] | None = None) -> TrainingResult:
        """Observer, training, then up to ``rounds`` rounds of smoothing with the learned model and retraining,
        on one record validated on time blocks of it (``config.validation_fraction``, ``validation_layout``).

        Parameters
        ----------
        system : System
            The prior (and the estimators' Q, R, P0 used by the smoother).
        y : array_like, shape (T, m)
            Measurements of the training record.
        u : array_like, shape (T, p)
            Inputs.
        dt : float
            Sample period, s.
        progress : callable, optional
            ``progress(epoch, loss)`` of every round's training.

        Returns
        -------
        TrainingResult
            The kept round's result; its model's meta ``"observer"`` holds ``kind``, ``rounds`` (asked),
            ``kept_round`` and ``misfit`` per round run (mean whitened squared innovation of the learned
            model's smoother on the training record; only computed when ``rounds > 0``).

        Raises
        ------
        InvalidInput
            Whatever `models.training.train_knode` rejects.
        """
        y, u = np.asarray(y, dtype=float), np.asarray(u, dtype=float).reshape(len(y), -1)
        zeta = self.observe(system, y, u, dt)
        config, rounds = self.config, self.rounds
        if self.observer == "joint":   # the observer's states start the joint fit; no rounds after it
            from learnest.estimators.joint_training import train_jointly

            result = train_jointly(system, y, u, dt, zeta, config, progress=progress)
            result.model.meta["observer"] = {"kind": self.kind, "rounds": rounds, "kept_round": 0, "misfit": []}
            return result
        results = [train_knode(system, zeta, u, dt, config, progress=progress)]
        misfits: list[float] = []
        for round_ in range(rounds + 1 if rounds else 0):
            # score the model of round `round_` by how well its smoother explains y; its estimates train the next
            params = model_params(results[round_].model, zeta[0], dt)
            smoothed = run_urts(params, y, u)
            misfits.append(_misfit(smoothed.innovations, params.R))
            if (round_ and misfits[-1] >= misfits[-2]) or round_ == rounds:
                break                                       # no better than the round before it, or the last
            results.append(train_knode(system, smoothed.means, u, dt, config, progress=progress))
        kept = int(np.argmin(misfits)) if misfits else 0
        result = results[kept]
        result.model.meta["observer"] = {"kind": self.kind, "rounds": rounds, "kept_round": kept, "misfit": misfits}
        return result

    def fit_states(self, system: System, zeta: ArrayLike, u: ArrayLike, dt: float,
                   progress: Callable[[int, float], None] | None = None) -> TrainingResult:
        """Algorithm 1's training phase alone, on states ζ already observed: the observer is skipped because the
        states are given (every state measured, as in Table I's "full state" rows, or ζ of `observe` that a
        caller also uses for something else, as the diagnosis does), validated on time blocks of the record.

        Parameters
        ----------
        system : System
            The prior.
        zeta : array_like, shape (T, n)
            State observations, in the system's state units.
        u : array_like, shape (T, p)
            Inputs (may have width 0).
        dt : float
            Sample period, s.
        progress : callable, optional
            ``progress(epoch, mean_training_loss)`` after every epoch.

        Returns
        -------
        TrainingResult
            `models.training.train_knode`'s on these states with ``config``; the model's meta records no
            observer, since none ran.

        Raises
        ------
        InvalidInput
            With the joint observer or ``rounds > 0``, which need the measurements (use `fit`); whatever
            `models.training.train_knode` rejects.
        """
        if self.observer == "joint" or self.rounds:
            raise InvalidInput("fit_states trains once on given states; the joint fit and observer rounds need the "
                               "measurements: use fit")
        return train_knode(system, zeta, u, dt, self.config, progress=progress)

    def fit_flights(self, flights: Sequence[Flight], system: str = "quadrotor", validate: Sequence[str] | None = None,
                    blind_attitude: bool = True, blind_battery: bool = True,
                    progress: Callable[[int, float], None] | None = None) -> TrainingResult:
        """Algorithm 1 on flights of one vehicle: this observer on each flight's own measurements and inputs (each
        with its own thrust gain, battery and length), then one KNODE.

        One flight (and no ``validate``) is the paper's protocol exactly (`fit`: time blocks of the flight held
        out).  Several train one pooled loss over every training flight (`models.pooled_training.train_knode_pooled`)
        with whole flights held out for validation; ``config.validation_fraction``/``validation_layout`` are
        unused then, and the observer must be a filter or smoother without rounds.

        Parameters
        ----------
        flights : sequence of Flight
            The flights, distinct names.
        system : {"quadrotor", "crazyflie"}
            The prior (`estimators.prepared.FLIGHT_SYSTEMS`).
        validate : sequence of str, optional
            Names of the flights held out; default `estimators.flight_training.default_validation` (one in five,
            at least one of two or more).
        blind_attitude : bool
            Several flights: the residual is also blind to the attitude inputs (`models.training.attitude_blind`;
            the default, why there).  Ignored for one flight, which keeps the paper's protocol and the system's
            masks.
        blind_battery : bool
            Several flights, with ``blind_attitude``: blind to the battery voltage too
            (`models.training.BATTERY_INPUTS`; the default).
        progress : callable, optional
            ``progress(epoch, mean_training_loss)`` after every epoch.

        Returns
        -------
        TrainingResult
            Its model's meta holds ``training_flights`` and ``validation_flights`` (each
            `estimators.flight_training.flight_lineage`), ``validation`` (how it was validated), ``learned``
            (False when no epoch beat the prior on the held-out data: the model equals its prior),
            ``training_flight`` and ``training_flight_sha256`` (the first training flight's name; every training
            flight's sha256, so an evaluation excludes all of them), ``system``, ``training_profile`` (the
            flight's `ingest.profile.flight_profile`, or `pooled_profile` of the training flights), ``observer``;
            ``residual_blind`` (with several flights: every state and input the residual does not read).

        Raises
        ------
        InvalidInput
            No flight, a name given twice, a ``validate`` name not among the flights, every flight held out,
            flights of different vehicles (`check_one_vehicle`), or a joint observer or rounds with several
            flights; `models.inputs.MissingInputs` when the prior needs inputs a flight lacks.
        """
        flights = list(flights)
        names, held = _held_out(flights, validate)
        if len(flights) > 1 and (self.observer == "joint" or self.rounds):
            raise InvalidInput("a joint observer and observer rounds train on one record; several flights train "
                               "one pooled loss on a filter's or smoother's states")
        inputs = [flight_inputs(flight, system) for flight in flights]
        systems = [prior for prior, _, _ in inputs]
        check_one_vehicle(flights, systems, [gain for _, _, gain in inputs])
        trained = [i for i, h in enumerate(held) if not h]
        lineage = [flight_lineage(f, gain) for f, (_, _, gain) in zip(flights, inputs)]
        if len(flights) == 1:   # the paper's protocol: time blocks of the flight validate
            prior, u, _ = inputs[0]
            result = self.fit(prior, flights[0].measurements(), u, prior.dt, progress)
            profile, validation = flight_profile(flights[0]), "held-out time blocks of the flight"
        else:
            records = [TrainingRecord(f.name, self.observe(p, f.measurements(), u, p.dt), u, p.dt)
                       for f, (p, u, _) in zip(flights, inputs)]
            prior = attitude_blind(systems[trained[0]], blind_battery) if blind_attitude else systems[trained[0]]
            result = train_ensemble(prior, records, held, self.config, progress)
            result.model.meta["residual_blind"] = list(prior.residual_blind)
            result.model.meta["observer"] = {"kind": self.kind, "rounds": 0, "kept_round": 0, "misfit": []}
            profile, validation = pooled_profile([flights[i] for i in trained]), "held-out flights"
        result.model.meta.update(training_meta(prior))   # evaluations check it: older models saw the raw attitude
        result.model.meta.update({
            "system": prior.name, "training_flight": names[trained[0]],
            "training_flight_sha256": [sha for i in trained for sha in lineage[i]["sha256"]],
            "training_profile": profile, "training_flights": [lineage[i] for i in trained],
            "validation_flights": [lineage[i] for i, h in enumerate(held) if h], "validation": validation})
        return result


def _held_out(flights: list[Flight], validate: Sequence[str] | None) -> tuple[list[str], list[bool]]:
    """The flights' names and, per flight, whether it is held out whole (`Algorithm1.fit_flights`'s rules)."""
    if not flights:
        raise InvalidInput("training needs at least one flight")
    names = [f.name for f in flights]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InvalidInput(f"flight(s) given more than once: {', '.join(twice)}")
    if validate:
        unknown = [n for n in validate if n not in names]
        if unknown:
            raise InvalidInput(f"validation flight(s) {', '.join(unknown)} are not among the training set's flights "
                               f"({', '.join(names)})")
        held = [n in set(validate) for n in names]
    else:
        chosen = set(default_validation(len(flights)))
        held = [i in chosen for i in range(len(flights))]
    if all(held):
        raise InvalidInput(f"every flight is held out for validation ({', '.join(names)}): keep one to train on")
    return names, held


def train_ensemble(prior: System, records: list[TrainingRecord], held: list[bool], config: TrainingConfig,
                   progress: Callable[[int, float], None] | None) -> TrainingResult:
    """`models.pooled_training.train_members_pooled` with ``config.ensemble`` members from seeds ``seed, seed + 1,
    ...``; with more than one, the model's residual is their mean carrying the members
    (`models.ensemble.mean_residual`) and its meta's ``ensemble`` says how many were trained and each one's kept
    epoch."""
    results = train_members_pooled(prior, records, held, config, config.ensemble, progress)
    first = results[0]
    if len(results) == 1:
        return first
    model = first.model
    residual = mean_residual([r.model.residual for r in results if r.model.residual is not None])
    meta = {**model.meta, "ensemble": {"members": len(results), "seeds": [config.seed + k for k in range(len(results))],
                                       "best_epochs": [r.model.meta.get("best_epoch") for r in results]},
            "learned": any(r.learned for r in results), "seconds": first.seconds}
    if meta["learned"]:
        meta.pop("learned_note", None)
    return TrainingResult(HybridModel(model.system, model.kind, residual, meta), first.losses, first.seconds,
                          first.validation_losses)
