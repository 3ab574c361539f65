"""Named physical effects: parametric terms with units that can be added to a prior or a measurement model.

Dynamics effects are parameters of a system's `dynamics(x, u, params)` (their nominal value is what the
prior assumes).  Measurement effects describe how a Crazyflie accelerometer departs from an ideal one:

    acc_body(t) = S · R_mis(roll, pitch) · f_body(t - delay) + bias          (specific force, m/s², IMU)

with f_body = Rᵀ (p̈ + g ẑ) the true specific force in the mocap body frame.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.frames import GRAVITY, imu_misalignment, quat_to_matrix, world_acceleration

from . import crazyflie as cf

if TYPE_CHECKING:
    from .systems import System


@dataclass(frozen=True)
class Param:
    """One parameter of an effect.

    Attributes
    ----------
    name : str
        Name in fitted values (``"bias_x"``, ``"delay_s"``, ...).
    unit : str
        Its unit (``"m/s²"``, ``"s"``, ``"rad"``, ``""`` for a pure number).
    nominal : float
        The value that means "no effect" (what the prior or an ideal sensor assumes).
    lower, upper : float
        Bounds of the fit.
    key : str
        The system's dynamics parameter it sets (dynamics effects only).
    start : float or None
        Where a fit starts (default: ``nominal``).  Needed where the nominal "off" value is a flat point of
        the model (ground effect acts through r², a lag of 0 s is a switch): a fit started there never moves.
    scan_step : float or None
        Grid step of a coarse scan over [lower, upper] that picks the fit's start (None: no scan).  For a
        time shift: the residual oscillates in the delay on the scale of the signal's period, so a local fit
        from 0 stops in the nearest dip, short of the true delay.
    """

    name: str
    unit: str
    nominal: float
    lower: float
    upper: float
    key: str = ""           # the system's dynamics parameter it sets (dynamics effects)
    start: float | None = None
    scan_step: float | None = None

    @property
    def initial(self) -> float:
        """Where a fit of this parameter starts: ``start``, else ``nominal``."""
        return self.nominal if self.start is None else self.start


@dataclass(frozen=True)
class Effect:
    """A named physical effect: parameters with units, added to a prior or to the accelerometer model.

    Attributes
    ----------
    id : str
        Key in ``LIBRARY`` (``"accel_bias"``, ``"cart_friction"``, ...).
    system : str
        The system it belongs to.
    target : {"dynamics", "measurement"}
    params : tuple of Param
    description : str
    """

    id: str
    system: str
    target: str             # "dynamics" or "measurement"
    params: tuple
    description: str

    @property
    def names(self) -> list[str]:
        """The parameters' names."""
        return [p.name for p in self.params]

    def nominal(self) -> dict:
        """{name: nominal value}: the effect switched off."""
        return {p.name: p.nominal for p in self.params}

    def equation(self, values: dict) -> str:
        """The fitted effect as a human-readable term (pysindy-style)."""
        # a dimensionless parameter (unit "1") prints bare: "gamma = 1.155", not "gamma = 1.155 1"
        return f"{self.id}: " + ", ".join(f"{p.name} = {values[p.name]:.4g} {'' if p.unit == '1' else p.unit}".rstrip()
                                          for p in self.params)


def _dyn(effect_id, system, description, *params):
    return Effect(effect_id, system, "dynamics", tuple(params), description)


def _meas(effect_id, description, *params):
    return Effect(effect_id, "quadrotor", "measurement", tuple(params), description)


# systems whose flights carry the accelerometer the measurement effects describe (they are listed once,
# under "quadrotor", and shared)
ACCELEROMETER_SYSTEMS = ("quadrotor", "crazyflie")
# a fit of these starts at the published value: their "off" value (0) is a flat point of the model
_START_AT_PUBLIC = ("r_m", "tau_s")


def crazyflie_effects(prior: dict | None = None) -> list[Effect]:
    """The Crazyflie prior's physical effects (`models.crazyflie.EFFECTS`), nominal at ``prior``'s values.

    Ids, parameters and one-line equations come from `models.crazyflie.EFFECTS`, units from ``UNITS``,
    bounds from ``BOUNDS``; the nominal value of each parameter is the prior's (default
    `models.crazyflie.IDENTIFIED`, the values fitted on the real NanoBench flights).  A parameter's key is
    its own name: the `Crazyflie` system's parameters carry the contract's names.
    """
    prior = cf.IDENTIFIED if prior is None else prior
    return [_dyn(effect_id, "crazyflie", spec["equation"],
                 *(Param(name, cf.UNITS[name], float(prior[name]), *cf.BOUNDS[name], key=name,
                         start=_crazyflie_start(name, float(prior[name])))
                   for name in spec["params"]))
            for effect_id, spec in cf.EFFECTS.items()]


def _crazyflie_start(name: str, nominal: float) -> float:
    """A fit's starting value: the published one where 0 is a flat point, and never on a bound (scipy's
    bounded trust region started on a bound takes vanishing steps and stops there)."""
    lower, upper = cf.BOUNDS[name]
    value = float(cf.PUBLIC[name]) if name in _START_AT_PUBLIC else nominal
    margin = 0.01 * (upper - lower)
    return float(np.clip(value, lower + margin, upper - margin))


LIBRARY = {e.id: e for e in [
    # -- cartpole (eq. 9): physical constants of the prior, and viscous friction the prior lacks
    _dyn("cart_mass", "cartpole", "cart mass differs from the prior's", Param("m_c", "kg", 1.0, 0.1, 10.0, "m_c")),
    _dyn("pole_mass", "cartpole", "pole mass differs from the prior's", Param("m_p", "kg", 0.1, 0.01, 2.0, "m_p")),
    _dyn("pole_length", "cartpole", "pole half-length differs", Param("l", "m", 0.5, 0.05, 3.0, "l")),
    _dyn("cart_friction", "cartpole", "viscous friction on the cart, F_f = -b·ṗ",
         Param("b", "N·s/m", 0.0, -1.0, 20.0, "b")),
    # -- ground robot (eq. 10)
    _dyn("quadratic_drag", "robot", "aerodynamic drag -c·v², c = 0.5·S·C_D/m",
         Param("c", "1/m", 0.0, -1.0, 5.0, "c_quad")),
    _dyn("linear_drag", "robot", "rolling resistance -k·v", Param("k", "1/s", 0.0, -1.0, 5.0, "k_lin")),
    _dyn("steering_offset", "robot", "steering angle offset δ + δ0",
         Param("delta0_rad", "rad", 0.0, -0.5, 0.5, "delta0")),
    # -- quadrotor translational dynamics: what the flown trajectory makes identifiable from [p, v, a]
    _dyn("accel_decay", "quadrotor", "acceleration relaxes, ȧ = -k·a (Singer model)",
         Param("k", "1/s", 0.0, -5.0, 50.0, "decay")),
    _dyn("harmonic_motion", "quadrotor", "periodic flight, horizontal jerk -ω²·v",
         Param("omega", "rad/s", 0.0, 0.0, 10.0, "omega")),
    # -- quadrotor accelerometer
    _meas("accel_bias", "constant accelerometer offset (body frame)",
          Param("bias_x", "m/s²", 0.0, -3.0, 3.0), Param("bias_y", "m/s²", 0.0, -3.0, 3.0),
          Param("bias_z", "m/s²", 0.0, -3.0, 3.0)),
    _meas("accel_scale", "accelerometer scale factors (1 = nominal)",
          Param("scale_x", "", 1.0, 0.5, 1.5), Param("scale_y", "", 1.0, 0.5, 1.5),
          Param("scale_z", "", 1.0, 0.5, 1.5)),
    # the total lag of the accelerometer behind the mocap: a time-stamp delay plus its own low-pass's group
    # delay (the data cannot tell them apart; a 30 Hz first-order filter adds ≈ 5 ms)
    _meas("accel_delay", "accelerometer lags the mocap (stamp delay + its filter's group delay)",
          Param("delay_s", "s", 0.0, -0.2, 0.2, scan_step=0.005)),
    _meas("accel_misalignment", "IMU frame tilted against the mocap body frame",
          Param("roll_rad", "rad", 0.0, -0.3, 0.3), Param("pitch_rad", "rad", 0.0, -0.3, 0.3)),
    # -- Crazyflie prior driven by motors and battery: mass, battery_thrust, rotor_drag, ...
    *crazyflie_effects(),
]}


def effects_for(system: str, target: str | None = None) -> list[Effect]:
    """The library's effects of ``system``, optionally only ``"dynamics"`` or ``"measurement"`` ones.

    Raises
    ------
    InvalidInput
        If none is found.
    """
    found = [e for e in LIBRARY.values() if _belongs(e, system) and (target is None or e.target == target)]
    if not found:
        raise InvalidInput(f"no effects known for system {system!r}")
    return found


def _belongs(effect: Effect, system: str) -> bool:
    return effect.system == system or (effect.target == "measurement" and system in ACCELEROMETER_SYSTEMS)


def dynamics_params(system: System, values: dict, effects: Iterable[Effect]) -> dict:
    """The system's prior parameters with the fitted dynamics effects substituted."""
    params = dict(system.prior_params)
    for effect in effects:
        for p in effect.params:
            params[p.key] = values[p.name]
    return params


# -- the accelerometer model -----------------------------------------------------------------------------
def tilt_matrix(roll: float, pitch: float) -> np.ndarray:
    """R (body <- IMU); with forces as rows, f @ R is what the tilted IMU reads and g @ R.T undoes it."""
    return imu_misalignment(roll, pitch).as_matrix()


def delayed(values: np.ndarray, dt: float, delay: float) -> np.ndarray:
    """values(t - delay) on the same grid, by a Fourier phase ramp on the zero-padded, mean-free signal.

    Linear interpolation would average neighbouring samples at fractional delays and so lower the noise
    power of the shifted signal: a least-squares fit then prefers half-sample delays and shrinks the
    estimate.  A phase ramp shifts without changing the power, so the fit is a true cross-correlation."""
    if delay == 0.0:
        return values
    mean = values.mean(axis=0)
    n = len(values)
    size = 1 << int(np.ceil(np.log2(2 * n)))
    spectrum = np.fft.rfft(values - mean, n=size, axis=0)
    freqs = np.fft.rfftfreq(size, d=dt)
    shifted = np.fft.irfft(spectrum * np.exp(-2j * np.pi * freqs * delay)[:, None], n=size, axis=0)[:n]
    return shifted + mean


def predict_acc_body(f_body: np.ndarray, t: np.ndarray, values: dict) -> np.ndarray:
    """What the accelerometer reads (m/s², IMU frame) for true specific force f_body (T, 3) at times t (s).

    ``values`` holds any of ``delay_s``, ``roll_rad``, ``pitch_rad``, ``scale_x..z``, ``bias_x..z`` (m/s²);
    missing ones are nominal.  Returns shape (T, 3).
    """
    shifted = delayed(f_body, float(t[1] - t[0]), values.get("delay_s", 0.0))
    tilted = shifted @ tilt_matrix(values.get("roll_rad", 0.0), values.get("pitch_rad", 0.0))
    scale = np.array([values.get(f"scale_{a}", 1.0) for a in "xyz"])
    bias = np.array([values.get(f"bias_{a}", 0.0) for a in "xyz"])
    return tilted * scale + bias


def correct_acc_body(acc_body: np.ndarray, t: np.ndarray, values: dict) -> np.ndarray:
    """Invert the accelerometer model: the specific force the IMU would have read were it ideal.

    acc_body (T, 3) m/s², t (T,) s, ``values`` as in `predict_acc_body`; returns (T, 3) m/s², body frame.
    """
    scale = np.array([values.get(f"scale_{a}", 1.0) for a in "xyz"])
    bias = np.array([values.get(f"bias_{a}", 0.0) for a in "xyz"])
    untilted = ((acc_body - bias) / scale) @ tilt_matrix(values.get("roll_rad", 0.0), values.get("pitch_rad", 0.0)).T
    return delayed(untilted, float(t[1] - t[0]), -values.get("delay_s", 0.0))


# a quadrotor's accelerometer sees horizontal (body x/y) specific force only through rotor drag; below
# this rms the x/y scale factors cannot be separated from reference errors and are held at 1
MIN_HORIZONTAL_FORCE_MS2 = 0.5


def unidentifiable_scales(f_body: np.ndarray) -> dict[str, str]:
    """{"scale_x"/"scale_y": why} for the body axes whose specific force f_body (N, 3) m/s² is below
    ``MIN_HORIZONTAL_FORCE_MS2`` rms: such a scale factor is not identifiable and is held at 1."""
    frozen = {}
    for axis, j in (("x", 0), ("y", 1)):
        rms = float(np.sqrt(np.mean(f_body[:, j] ** 2)))
        if rms < MIN_HORIZONTAL_FORCE_MS2:
            frozen[f"scale_{axis}"] = (f"body-{axis} specific force is only {rms:.2f} m/s² rms (rotor drag): "
                                       f"scale_{axis} is not identifiable in this flight and is held at 1")
    return frozen


def specific_force_body(a_world: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """f_body = Rᵀ (a + g ẑ): what an ideal body-frame accelerometer reads for world acceleration a.

    a_world (T, 3) m/s², quat (T, 4) scalar-last body-to-world -> (T, 3) m/s².
    """
    return np.einsum("tji,tj->ti", quat_to_matrix(quat), a_world + np.array([0.0, 0.0, GRAVITY]))


def world_from_body(acc_body: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """a_meas = R acc_body - g ẑ from a body-frame reading in m/s² (the Flight's convention).

    acc_body (T, 3) m/s², quat (T, 4) scalar-last -> (T, 3) m/s², world frame.
    """
    return world_acceleration(acc_body / GRAVITY, quat)
