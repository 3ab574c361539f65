"""The sensors (SensorModel, every parameter known) and their records: mocap and IMU sampled from the
true states, with noise, bias, scale, misalignment, low-pass and delay as set."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..frames import GRAVITY, imu_misalignment
from .trajectories import SIM_RATE_HZ, Reference
from .vehicle import States

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation


@dataclass
class SensorModel:
    """The simulated sensors' settings: rates, noise and IMU effects (the defaults add noise and no effects).

    Attributes
    ----------
    mocap_rate_hz : float
        Mocap sample rate, Hz.
    mocap_position_noise_m : float
        Standard deviation of the white position noise, m.
    mocap_attitude_noise_rad : float
        Standard deviation of each component of a rotation-vector jitter applied in the body frame, rad.
    imu_rate_hz : float
        IMU sample rate, Hz.
    acc_noise_g : float
        Standard deviation of the accelerometer's white noise, g.
    gyro_noise_rad_s : float
        Standard deviation of the gyro's white noise, rad/s.
    bias : (3,) tuple
        Accelerometer bias, m/s², IMU axes.
    scale : (3,) tuple
        Accelerometer scale factor per IMU axis (applied before the bias).
    delay_s : float
        How far the IMU lags the mocap, s (> 0: its values are older than its stamps).
    misalignment : (2,) tuple
        (roll, pitch) of the IMU frame vs the body frame, rad.
    lowpass_hz : float or None
        Cut-off of a first-order low-pass on the accelerometer (run on the 1 kHz grid), Hz; None: no filter.
    """
    mocap_rate_hz: float = 100.0
    mocap_position_noise_m: float = 0.0005
    mocap_attitude_noise_rad: float = 0.002
    imu_rate_hz: float = 500.0
    acc_noise_g: float = 0.02
    gyro_noise_rad_s: float = 0.005
    bias: tuple = (0.0, 0.0, 0.0)            # m/s², IMU axes
    scale: tuple = (1.0, 1.0, 1.0)
    delay_s: float = 0.0                     # > 0: the IMU lags the mocap
    misalignment: tuple = (0.0, 0.0)         # (roll, pitch) rad of the IMU frame vs the body frame
    lowpass_hz: float | None = None          # first-order, on the accelerometer

    @classmethod
    def ideal(cls, **changes) -> SensorModel:
        """No noise and no effects (then only the file formats' quantisation separates files from truth)."""
        return cls(**{"mocap_position_noise_m": 0.0, "mocap_attitude_noise_rad": 0.0, "acc_noise_g": 0.0,
                      "gyro_noise_rad_s": 0.0, **changes})

    def changes(self) -> dict:
        """Every setting that differs from the defaults (noise, rates and effects), for READMEs."""
        nominal = SensorModel()
        return {name: value for name, value in vars(self).items() if value != getattr(nominal, name)}

    def accelerometer_group_delay_s(self) -> float:
        """Low-frequency group delay of the accelerometer's low-pass as simulated (0 without one), s.

        Computed from the discrete filter `_first_order_lowpass` runs (pole-matched, 1 kHz): -dφ/dω at
        0.1 Hz, where a flight's manoeuvres live.  This is the lag a pure delay fitted to the filtered
        signal finds, on top of ``delay_s`` (≈ 4.8 ms at 30 Hz, half a 1-ms step below 1/(2π·30 Hz))."""
        if not self.lowpass_hz:
            return 0.0
        from scipy.signal import group_delay  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

        b, a = _first_order_lowpass_coefficients(self.lowpass_hz, SIM_RATE_HZ)
        _, samples = group_delay((b, a), w=[0.1], fs=SIM_RATE_HZ)
        return float(samples[0]) / SIM_RATE_HZ

    def misalignment_rotation(self) -> Rotation:
        """Rotation body <- IMU of this sensor's mounting tilt."""
        return imu_misalignment(*self.misalignment)     # body <- IMU


@dataclass
class Mocap:
    """The mocap records of a simulated flight.

    Attributes
    ----------
    t : (N,) array
        Sample times, s (simulation time).
    p : (N, 3) array
        Positions with noise, m, world frame.
    quat : (N, 4) array
        Attitudes with noise, body -> world, scalar last.
    truth : States
        The true states at `t`.
    """
    t: np.ndarray          # s, simulation time
    p: np.ndarray          # m, with noise
    quat: np.ndarray       # with noise
    truth: States


@dataclass
class Imu:
    """The IMU records of a simulated flight.

    Attributes
    ----------
    t : (N,) array
        Stamps, s (simulation time); with delay_s > 0 the values are those of t - delay_s.
    acc_g : (N, 3) array
        Specific force in the IMU frame, g (with scale, bias, low-pass, delay and noise as set).
    gyro : (N, 3) array
        Body rates in the IMU frame, rad/s (with delay and noise only).
    truth : States
        The true states at the stamps.
    setpoint : (N, 3) array
        The reference position at the stamps, m.
    """
    t: np.ndarray          # s, simulation time (the stamps; with delay_s the values are older)
    acc_g: np.ndarray      # IMU frame, g
    gyro: np.ndarray       # IMU frame, rad/s
    truth: States          # at the stamps
    setpoint: np.ndarray   # the reference position at the stamps (m)


def sample_times(end_s: float, rate_hz: float) -> np.ndarray:
    """Sample times 0, 1/rate_hz, 2/rate_hz, ... up to end_s (included when on the grid), s; shape (N,)."""
    return np.arange(int(np.floor(end_s * rate_hz + 1e-9)) + 1) / rate_hz


def _noise(seed: int, stream: int, shape, std: float) -> np.ndarray:
    """White noise of one sensor stream; each stream has its own generator, so changing one sensor's
    settings leaves the others' noise as it was."""
    if std == 0:
        return np.zeros(shape)
    return np.random.default_rng([seed, stream]).normal(0.0, std, shape)


def sample_mocap(truth: States, sensors: SensorModel, seed: int) -> Mocap:
    """Sample the mocap at sensors.mocap_rate_hz over [0, truth.t[-1]], with position and attitude noise.

    Parameters
    ----------
    truth : States
        The true states on the simulation grid.
    sensors : SensorModel
        Rate and noise levels.
    seed : int
        Noise seed (each sensor stream draws from its own generator).

    Returns
    -------
    Mocap
    """
    from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

    t = sample_times(truth.t[-1], sensors.mocap_rate_hz)
    exact = truth.at(t)
    p = exact.p + _noise(seed, 1, exact.p.shape, sensors.mocap_position_noise_m)
    quat = exact.quat
    if sensors.mocap_attitude_noise_rad > 0:
        jitter = Rotation.from_rotvec(_noise(seed, 2, exact.p.shape, sensors.mocap_attitude_noise_rad))
        quat = (Rotation.from_quat(exact.quat) * jitter).as_quat()
    return Mocap(t, p, quat, exact)


def _first_order_lowpass_coefficients(cutoff_hz: float, rate_hz: float) -> tuple[list[float], list[float]]:
    """(b, a) of the pole-matched first-order low-pass y[k] = α x[k] + (1 − α) y[k−1]."""
    alpha = 1.0 - math.exp(-2 * math.pi * cutoff_hz / rate_hz)
    return [alpha], [1.0, alpha - 1.0]


def _first_order_lowpass(values: np.ndarray, cutoff_hz: float, rate_hz: float) -> np.ndarray:
    """1/(τs + 1) as the pole-matched recursion y[k] = α x[k] + (1 − α) y[k−1], started in steady state at
    the first value.  It uses x[k], not the zero-order hold's x[k−1], so it leads that by one 1-kHz step."""
    from scipy.signal import lfilter, lfilter_zi  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    b, a = _first_order_lowpass_coefficients(cutoff_hz, rate_hz)
    zi = lfilter_zi(b, a)[:, None] * values[:1]
    return lfilter(b, a, values, axis=0, zi=zi)[0]


def _delayed(t_sim, values, t_stamps, delay_s: float) -> np.ndarray:
    """Values at t_stamps − delay (held at the first value before the start)."""
    return np.column_stack([np.interp(t_stamps - delay_s, t_sim, values[:, j]) for j in range(values.shape[1])])


def sample_imu(truth: States, ref: Reference, sensors: SensorModel, seed: int) -> Imu:
    """Sample the IMU at sensors.imu_rate_hz over [0, truth.t[-1]].

    The true body-frame specific force is rotated into the IMU frame, scaled, biased, low-passed (if set),
    delayed, converted to g and given noise; body rates are rotated, delayed and given noise.

    Parameters
    ----------
    truth : States
        The true states on the simulation grid.
    ref : Reference
        The reference; its position, interpolated at the stamps, becomes ``Imu.setpoint``.
    sensors : SensorModel
        Rate, noise and effects.
    seed : int
        Noise seed (each sensor stream draws from its own generator).

    Returns
    -------
    Imu
    """
    t = sample_times(truth.t[-1], sensors.imu_rate_hz)
    to_imu = sensors.misalignment_rotation().inv()
    force = to_imu.apply(truth.specific_force_body()) * sensors.scale + sensors.bias
    if sensors.lowpass_hz:
        force = _first_order_lowpass(force, sensors.lowpass_hz, SIM_RATE_HZ)
    acc = _delayed(truth.t, force, t, sensors.delay_s) / GRAVITY + _noise(seed, 3, (len(t), 3), sensors.acc_noise_g)
    rates = _delayed(truth.t, to_imu.apply(truth.omega), t, sensors.delay_s)
    gyro = rates + _noise(seed, 4, (len(t), 3), sensors.gyro_noise_rad_s)
    setpoint = np.column_stack([np.interp(t, ref.t, ref.p[:, j]) for j in range(3)])
    return Imu(t, acc, gyro, truth.at(t), setpoint)
