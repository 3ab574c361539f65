"""`KNODE`: Algorithm 1 (`algorithm1.Algorithm1`) as an estimator object a notebook user fits
(pysindy/scikit-learn habit).

Hyperparameters go to the constructor, `fit(flight)` (or `fit(flights)`, several flights of one vehicle) runs
the pre-training observer and the training and returns ``self``; what was learned ends in ``_``.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.models.inputs import prior_for_flights
from learnest.models.presets import CRAZYFLIE_TRAINING

from .group_training import GROUP_BY, train_flights
from .prepared import FLIGHT_SYSTEMS


class KNODE:
    """A knowledge-based neural ODE, f = f_prior + Δθ, trained on one flight (paper Algorithm 1) or on several
    flights of one vehicle (one pooled loss, whole flights held out for validation).

    Parameters
    ----------
    system : str or None
        The prior: ``"quadrotor"`` (the paper's kinematic chain x = [p, v, a], 9 states) or ``"crazyflie"``
        (the same states driven by the motor PWM and battery voltage the flight must carry).  None (the
        default): chosen from the flights `fit` gets, as ``learnest demo`` chooses it
        (`models.inputs.prior_for_flights`): "crazyflie" when every flight carries motor PWM and battery
        voltage, else "quadrotor"; ``system_`` says which.
    hidden : int
        Neurons of the residual's hidden tanh layer (Sec. V-C: 16).
    epochs : int
        Full-batch Adam epochs (Sec. V-C: 150).
    lr : float
        Adam learning rate.
    validation_fraction : float
        Of one flight: share of the record held out in time blocks; the weights of the epoch that predicts
        it best are kept.  Several flights are validated on whole held-out flights instead.
    seed : int
        Seed of the network's initial weights.
    group_by : str
        Several flights: the groups held out in turn to choose how much of the residual to keep
        (`estimators.group_training`): ``"family"`` (the trajectory family the logs declare; the default),
        ``"name:REGEX"`` (one capture group of the flight's name) or ``"none"`` (the whole residual).
    noise : {"identified", "paper"}
        Identify the process noise of the model and of its prior on the training flights (the default; stored
        with ``model_``: `learnest.ukf`, `learnest.mhe` and `learnest.evaluate` run each model with its own), or
        keep the system's fixed noise (the paper's protocol).

    Attributes
    ----------
    system_ : str
        The prior the model was trained with: ``system``, or the one chosen from the flights.
    model_ : HybridModel
        The trained discrete model (prior + residual, RK4), ready for `learnest.ukf` / `learnest.mhe`.
    losses_ : list of float
        Training loss (eq. 8) per epoch.
    validation_losses_ : list of float
        Held-out loss per epoch (empty when nothing is held out).
    seconds_ : float
        Wall time of the epochs, s.
    learned_ : bool
        False when no epoch predicted the held-out data better than the prior: ``model_`` equals its prior
        (``model_.meta["learned_note"]`` says so in words).
    residual_scale_ : float
        The scale s of the residual kept, f = f_prior + s Δθ (1.0: the whole residual).
    residual_scale_note_ : str
        How it was chosen, or why no scale was chosen (one trajectory family: nothing to hold out).
    training_flights_, validation_flights_ : list of str
        Names of the flights trained on and of those held out whole (empty for one flight).

    Examples
    --------
    >>> import learnest as le
    >>> flights = le.read_flights(["sample_logs/circle_rep1.csv", "sample_logs/circle_rep2.csv"])
    >>> knode = le.KNODE(epochs=20).fit(flights[0])
    >>> knode.system_                      # circle_rep1 logs no motors: the kinematic prior
    'quadrotor'
    >>> knode.model_
    HybridModel(quadrotor, knode)
    """

    def __init__(self, system: str | None = None, hidden: int = CRAZYFLIE_TRAINING.hidden,
                 epochs: int = CRAZYFLIE_TRAINING.epochs, lr: float = CRAZYFLIE_TRAINING.lr,
                 validation_fraction: float = CRAZYFLIE_TRAINING.validation_fraction, seed: int = 0,
                 group_by: str = GROUP_BY, noise: str = "identified") -> None:
        self.system, self.hidden, self.epochs, self.lr = system, hidden, epochs, lr
        self.validation_fraction, self.seed, self.group_by = validation_fraction, seed, group_by
        self.noise = noise

    def fit(self, flights: Flight | Sequence[Flight], progress: Callable[[int, float], None] | None = None,
            validate: Sequence[str] | None = None) -> KNODE:
        """Train on one flight, or on several flights of one vehicle.

        Parameters
        ----------
        flights : Flight or sequence of Flight
            The training flight(s) (position and world-frame acceleration are the measurements).  Several
            flights train one residual on one pooled loss (`estimators.algorithm1.Algorithm1.fit_flights`), its
            scale chosen on held-out groups of them (``group_by``, `estimators.group_training.train_flights`).
        progress : callable, optional
            Called as ``progress(epoch, mean_training_loss)`` after every epoch.
        validate : sequence of str, optional
            Names of the flights held out whole (default with several flights: one in five).

        Returns
        -------
        KNODE
            ``self``, with the fitted attributes set.

        Raises
        ------
        InvalidInput
            If ``system`` cannot be fitted on a flight, an item is not a Flight, the flights lack the inputs
            the asked-for prior needs, or they are not one vehicle's (the message names them).
        """
        if self.system is not None and self.system not in FLIGHT_SYSTEMS:
            raise InvalidInput(f"system {self.system!r} cannot be fitted on a flight; choose one of "
                               f"{', '.join(FLIGHT_SYSTEMS)}")
        given: list = [flights] if isinstance(flights, Flight) else list(flights) \
            if isinstance(flights, (list, tuple)) else [flights]
        wrong = [type(f).__name__ for f in given if not isinstance(f, Flight)]
        if wrong or not given:
            raise InvalidInput(f"fit needs a Flight or a list of Flights (learnest.read_flights), got "
                               f"{wrong[0] if wrong else 'an empty list'}")
        system = self.system or prior_for_flights(given)
        config = replace(CRAZYFLIE_TRAINING, hidden=self.hidden, epochs=self.epochs, lr=self.lr,
                         validation_fraction=self.validation_fraction, seed=self.seed)
        result = train_flights(given, system, config, self.group_by, validate, progress=progress, noise=self.noise)
        self.system_ = system
        self.model_ = result.model
        self.losses_, self.validation_losses_ = result.losses, result.validation_losses
        self.seconds_ = result.seconds
        self.learned_ = result.learned
        self.residual_scale_ = float(result.model.meta.get("residual_scale", 1.0))
        self.residual_scale_note_ = str(result.model.meta.get("residual_scale_note", ""))
        self.training_flights_ = [f["name"] for f in result.model.meta.get("training_flights", [])]
        self.validation_flights_ = [f["name"] for f in result.model.meta.get("validation_flights", [])]
        return self

    def __repr__(self) -> str:
        return (f"KNODE(system={self.system!r}, hidden={self.hidden}, epochs={self.epochs}, lr={self.lr}, "
                f"validation_fraction={self.validation_fraction}, seed={self.seed}, group_by={self.group_by!r}, "
                f"noise={self.noise!r})")
