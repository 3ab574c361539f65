"""The Crazyflie's residual problem for effect selection: what the accelerometer reads against what the
inputs (motor PWM, battery voltage, mocap attitude and velocity) predict through `models.crazyflie`.

Each row is one kept sample of a flight (every `ROW_STRIDE`-th) with 6 columns (m/s², body frame):

- columns 0-2, inputs: acc_body − A(f_inputs), with f_inputs = `models.crazyflie.identify.predict_body_force` (the
  thrust map, ground effect and rotor drag at the effects' parameters, the motor lag as a first-order
  filter) and A the accelerometer model `models.effects.predict_acc_body` (bias, scale, delay, tilt);
- columns 3-5, mocap: acc_body − A(f_mocap), with f_mocap = Rᵀ (p̈ + g e₃) from the mocap position.

Both sides of both blocks are low-passed alike: at `models.crazyflie.identify.LOWPASS_HZ` (5 Hz, 2nd-order
Butterworth, zero phase), the mocap block then again at `MOCAP_LOWPASS_HZ` (2 Hz).  The mocap block sees
only the accelerometer effects: it is what tells an accelerometer scale error from a payload, which
through the inputs alone act identically (both scale T/m).  Samples the recorder interpolated across
gaps and the filter edges are left out (`models.crazyflie.identify.flight_arrays`).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight

from ..effects import (
    Effect,
    crazyflie_effects,
    effects_for,
    predict_acc_body,
    specific_force_body,
    unidentifiable_scales,
)
from ..inputs import system_inputs
from ..residual_problem import ResidualProblem
from ..systems import Crazyflie
from . import prior as cf
from .excitation import excitation, undetermined_params
from .identify import FlightArrays, flight_arrays, lowpass, predict_body_force

# ground effect is below 0.1 % of thrust above ~10 rotor radii: without samples that low r_m is not fitted
GROUND_EFFECT_HEIGHT_M = 10 * cf.BITCRAZE_ROTOR_RADIUS_M
MIN_GROUND_SAMPLES = 50
# mocap acceleration is position noise differentiated twice (it grows as f²): its block is low-passed
# further, on both sides, so that it does not swamp the accelerometer's own noise
MOCAP_LOWPASS_HZ = 2.0
# an effect must lower the held-out (blocked CV) error by 0.5 % to be claimed: below that, what it fits
# is a discretisation detail of the data (a ~1 ms shift between mocap and accelerometer on simulated
# flights), not a physical effect worth reporting
CRAZYFLIE_MIN_CV_GAIN = 0.005
# the residual is low-passed at 5 Hz: every 4th sample (25 Hz at a 100 Hz log) carries all it holds, and
# the fits run 4 times faster
ROW_STRIDE = 4
SHAPE_PARAMS = ("q_pwm2",)   # the thrust map's shape: no candidate, fitted only by the thrust map's fit
LINEAR = ("m_kg", "k_xy", "k_z")   # parameters the predicted force is linear in (through 1/m_kg for the mass)
MIN_ROWS = 50      # rows (25 Hz): 2 s of flight, the least a fit of a few parameters and its bootstrap need


@dataclass
class CrazyflieData:
    """One flight's arrays for the residual: `FlightArrays` plus the mocap-derived specific force."""

    arrays: FlightArrays
    t: np.ndarray          # (T,) s
    f_mocap: np.ndarray    # (T, 3) body-frame specific force from the mocap position, m/s², MOCAP_LOWPASS_HZ
    acc_mocap: np.ndarray  # (T, 3) the accelerometer low-passed alike, m/s²

    @property
    def rows(self) -> np.ndarray:
        """Indices of the samples that are rows: every `ROW_STRIDE`-th kept one."""
        return np.flatnonzero(self.arrays.keep)[::ROW_STRIDE]


def crazyflie_data(flight: Flight, prior: dict | None = None) -> CrazyflieData:
    """The residual's arrays for one flight.

    The observed specific force is the ``acc_body`` channel, or ``a_meas`` rotated into the body with
    gravity added when the flight lacks it.

    Raises
    ------
    models.inputs.MissingInputs
        If the flight lacks the motor PWM or battery voltage the prediction needs.
    """
    prior = cf.IDENTIFIED if prior is None else prior
    system_inputs(flight, Crazyflie(prior_params=dict(prior)))     # the clear message naming what is missing
    if "acc_body" not in flight.channels:
        flight = replace(flight, channels={**flight.channels,
                                           "acc_body": specific_force_body(flight.a_meas, flight.quat)})
    dt = flight.dt
    arrays = flight_arrays(flight, cf.thrust_source_of(prior))
    a_world = np.gradient(np.gradient(flight.p, dt, axis=0), dt, axis=0)
    f_mocap = lowpass(lowpass(specific_force_body(a_world, flight.quat), dt), dt, MOCAP_LOWPASS_HZ)
    return CrazyflieData(arrays, flight.t, f_mocap, lowpass(arrays.acc_body, dt, MOCAP_LOWPASS_HZ))


def crazyflie_problem(flights: list[Flight], prior: dict | None = None, name: str = "specific force") \
        -> ResidualProblem:
    """The `ResidualProblem` of the crazyflie system on ``flights`` (see the module's docstring).

    Parameters
    ----------
    flights : list of Flight
        With mocap, ``motors`` (T, 4) PWM, ``vbat`` (T,) V and ideally ``acc_body`` (T, 3) m/s².
    prior : dict, optional
        The prior's parameters (`models.crazyflie.IDENTIFIED` keys, the default): the dynamics effects'
        nominal values, and the values of every parameter no effect sets.
    name : str
        The channel's name in reports.

    Returns
    -------
    ResidualProblem
        Candidates: the crazyflie dynamics effects and the accelerometer effects; rows the kept samples of
        every flight, 6 columns; blocks the flights when there are several.  Frozen: body x/y scale
        factors when that specific force is below `effects.MIN_HORIZONTAL_FORCE_MS2` rms, r_m when fewer
        than `MIN_GROUND_SAMPLES` samples are below `GROUND_EFFECT_HEIGHT_M`.
    """
    prior = dict(cf.IDENTIFIED if prior is None else prior)
    data = [crazyflie_data(f, prior) for f in flights]
    candidates = _candidates(prior)
    dynamic_names = [p.name for e in candidates if e.target == "dynamics" for p in e.params]
    # the prediction is linear in 1/m_kg, k_xy and k_z (and the lag and the low-pass are linear filters):
    # two runs of predict_body_force per value of the other parameters give it for every mass and drag
    nonlinear = [k for k in dynamic_names if k not in LINEAR]
    # the map's shape is no candidate effect, but a fit of the thrust map may move it
    nonlinear += [k for k in SHAPE_PARAMS if k in prior and k not in nonlinear]
    cache: dict[tuple, list[tuple[np.ndarray, np.ndarray]]] = {}

    def predicted(values: dict) -> list[np.ndarray]:
        key = tuple(values.get(k, prior[k]) for k in nonlinear)
        if key not in cache:
            params = {**prior, **dict(zip(nonlinear, key))}
            if len(cache) > 8:
                cache.clear()
            cache[key] = [(predict_body_force(d.arrays, {**params, "m_kg": 1.0, "k_xy": 0.0, "k_z": 0.0})[:, 2],
                           predict_body_force(d.arrays, {**params, "m_kg": np.inf, "k_xy": 1.0, "k_z": 1.0}))
                          for d in data]
        linear = {**prior, **{k: values[k] for k in LINEAR if k in values}}
        gains = np.array([linear["k_xy"], linear["k_xy"], linear["k_z"]])
        out = []
        for thrust, drag in cache[key]:
            force = drag * gains
            force[:, 2] += thrust / linear["m_kg"]
            out.append(force)
        return out

    measurement_names = [p.name for e in candidates if e.target == "measurement" for p in e.params]
    mocap_cache: dict[tuple, list[np.ndarray]] = {}

    def mocap_block(values: dict) -> list[np.ndarray]:
        key = tuple(values[k] for k in measurement_names)
        if key not in mocap_cache:
            mocap_cache.clear()   # the dynamics fits, most of the work, leave it unchanged
            mocap_cache[key] = [(d.acc_mocap - predict_acc_body(d.f_mocap, d.t, values))[d.rows] for d in data]
        return mocap_cache[key]

    def residual(values: dict, rows: np.ndarray) -> np.ndarray:
        parts = [np.hstack([(d.arrays.acc_body - predict_acc_body(f_inputs, d.t, values))[d.rows], mocap])
                 for d, f_inputs, mocap in zip(data, predicted(values), mocap_block(values))]
        return np.concatenate(parts)[rows]

    lengths = [len(d.rows) for d in data]
    if sum(lengths) < MIN_ROWS:
        raise InvalidInput(f"{', '.join(f.name for f in flights)}: only {sum(lengths)} usable samples for the "
                           f"specific-force residual (at least {MIN_ROWS} needed): the accelerometer holds too few "
                           "measured samples away from gaps and the record's ends")
    offsets = np.cumsum([0] + lengths)
    blocks = [np.arange(offsets[i], offsets[i + 1]) for i in range(len(data))] if len(data) > 1 else []
    frozen = _frozen_params(data)
    times = np.concatenate([d.t[d.rows] for d in data])
    stats = excitation(data, cf.thrust_source_of(prior))
    return ResidualProblem(name, candidates, residual, int(offsets[-1]), blocks, frozen, times,
                           undetermined_params(stats, candidates), stats)


def _candidates(prior: dict) -> list[Effect]:
    """The candidate effects for ``prior``'s thrust source: the crazyflie dynamics effects, then the
    accelerometer's.  The battery and the motors' heating act between a PWM and the thrust: a rotor speed or a
    thrust in N already carries both (a commanded thrust keeps a battery term: what the firmware's compensation
    leaves, `models.crazyflie`)."""
    skip = {"pwm": (), "thrust_n": ("motor_heating",)}.get(cf.thrust_source_of(prior),
                                                           ("battery_thrust", "motor_heating"))
    return [e for e in crazyflie_effects(prior) if e.id not in skip] + effects_for("crazyflie", "measurement")


def _frozen_params(data: list) -> dict:
    """{param: why} for the parameters these flights cannot identify: the scales the mocap's specific force
    cannot tell apart (`effects.unidentifiable_scales`), and the ground effect's r_m without enough samples
    near the floor."""
    frozen = unidentifiable_scales(np.concatenate([d.f_mocap[d.arrays.keep] for d in data]))
    low = sum(int(np.sum(d.arrays.z[d.arrays.keep] < GROUND_EFFECT_HEIGHT_M)) for d in data)
    if low < MIN_GROUND_SAMPLES:
        frozen["r_m"] = (f"only {low} samples below {GROUND_EFFECT_HEIGHT_M:.2f} m: ground effect is not "
                         f"identifiable on these flights and r_m is held at the prior's value")
    return frozen


def specific_force_rmse(problem: ResidualProblem, values: dict | None = None) -> float:
    """RMSE (m/s², body x/y/z pooled, after the 5 Hz low-pass) of the prediction from the inputs alone:
    the inputs block of ``problem`` at ``values`` (default: every candidate nominal, i.e. the prior)."""
    nominal = {k: v for e in problem.candidates for k, v in e.nominal().items()}
    r = problem.residual({**nominal, **(values or {})}, np.arange(problem.n_rows))[:, :3]
    return float(np.sqrt(np.mean(r**2)))
