"""Trajectories and the reference over the whole flight: sit, take off (minimum-jerk), hover, fly the
trajectory (its speed ramping up and down smoothly), hover, land, sit; all on the simulation's 1 kHz grid."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from learnest.errors import InvalidInput

SIM_RATE_HZ = 1000.0    # the simulation runs on this grid: the reference, the closed loop, the IMU filter


# -- quintic smoothstep: the building block of every smooth start and stop -------------------------------
def _smoothstep(u):
    """h(u) = 10u³ − 15u⁴ + 6u⁵ on [0, 1] (clipped) with h', h'' and the integral H: zero velocity and
    acceleration at both ends, so references start and stop without a jump in acceleration."""
    u = np.clip(u, 0.0, 1.0)
    h = u ** 3 * (10 - 15 * u + 6 * u * u)
    dh = 30 * u * u * (1 - u) ** 2
    ddh = 60 * u * (1 - u) * (1 - 2 * u)
    integral = u ** 4 * (2.5 - 3 * u + u * u)
    return h, dh, ddh, integral


def _minimum_jerk(t, start, stop, duration):
    """(p, v, a) of a rest-to-rest minimum-jerk move from start to stop; held at the ends."""
    h, dh, ddh, _ = _smoothstep(np.asarray(t, float) / duration)
    delta = np.asarray(stop, float) - np.asarray(start, float)
    return (start + h[:, None] * delta, (dh / duration)[:, None] * delta,
            (ddh / duration ** 2)[:, None] * delta)


# -- trajectories ------------------------------------------------------------------------------------------
@dataclass(kw_only=True)
class Trajectory:
    """A path p(s) in the nominal time s.  Flown over `duration_s`: the speed ds/dt ramps smoothly from
    0 to 1 over ramp_s, stays at 1, and ramps down over the last ramp_s, so s runs over [0, s_end]."""
    duration_s: float = 10.0
    ramp_s: float = 1.5

    @property
    def s_end(self) -> float:
        """Nominal time at the end of the trajectory, s: duration_s - ramp_s (each speed ramp covers ramp_s / 2)."""
        return self.duration_s - self.ramp_s

    def path(self, s):
        """(p, dp/ds, d²p/ds²), each (N, 3)."""
        raise NotImplementedError

    def flown(self, tau):
        """(p, v, a, s) at times tau from the start of the flying part (held outside it)."""
        if self.duration_s < 2 * self.ramp_s:
            raise InvalidInput("duration_s must be at least twice ramp_s")
        tau = np.clip(np.asarray(tau, float), 0.0, self.duration_s)
        r = self.ramp_s
        s, s_dot, s_ddot = tau - r / 2, np.ones_like(tau), np.zeros_like(tau)
        up, down = tau < r, tau > self.duration_s - r
        h, dh, _, integral = _smoothstep(tau / r)
        s[up], s_dot[up], s_ddot[up] = r * integral[up], h[up], dh[up] / r
        h, dh, _, integral = _smoothstep((self.duration_s - tau) / r)
        s[down], s_dot[down], s_ddot[down] = self.s_end - r * integral[down], h[down], -dh[down] / r
        p, dp, ddp = self.path(s)
        return p, dp * s_dot[:, None], ddp * (s_dot ** 2)[:, None] + dp * s_ddot[:, None], s


@dataclass(kw_only=True)
class Circle(Trajectory):
    """Counter-clockwise circle at constant speed, starting at center + (radius, 0)."""
    radius: float = 0.5
    speed: float = 0.5
    altitude: float = 1.0
    center: tuple = (0.0, 0.0)

    def path(self, s):
        """(p, dp/ds, d²p/ds²) at nominal times s, each (N, 3): m, m/s, m/s²."""
        w = self.speed / self.radius
        angle = w * np.asarray(s, float)
        c, sn, zero = np.cos(angle), np.sin(angle), np.zeros_like(angle)
        p = np.column_stack([self.center[0] + self.radius * c, self.center[1] + self.radius * sn,
                             np.full_like(angle, self.altitude)])
        dp = self.radius * w * np.column_stack([-sn, c, zero])
        ddp = -self.radius * w * w * np.column_stack([c, sn, zero])
        return p, dp, ddp


@dataclass(kw_only=True)
class Figure8(Trajectory):
    """Lemniscate of Gerono: x = size·sin(Ωs), y = (size/2)·sin(2Ωs), Ω = 2π/period; starts at the centre."""
    size: float = 0.6
    period: float = 6.0
    altitude: float = 1.0
    center: tuple = (0.0, 0.0)

    def path(self, s):
        """(p, dp/ds, d²p/ds²) at nominal times s, each (N, 3): m, m/s, m/s²."""
        w = 2 * np.pi / self.period
        angle = w * np.asarray(s, float)
        zero = np.zeros_like(angle)
        half = self.size / 2
        p = np.column_stack([self.center[0] + self.size * np.sin(angle),
                             self.center[1] + half * np.sin(2 * angle), np.full_like(angle, self.altitude)])
        dp = np.column_stack([self.size * w * np.cos(angle), half * 2 * w * np.cos(2 * angle), zero])
        ddp = np.column_stack([-self.size * w * w * np.sin(angle), -half * 4 * w * w * np.sin(2 * angle), zero])
        return p, dp, ddp


@dataclass(kw_only=True)
class RandomWaypoints(Trajectory):
    """A C² cubic spline through `count` random points in `box` (seeded), knots spaced by distance/speed,
    zero velocity at both ends.  duration_s follows from the path (length / speed + ramp_s)."""
    count: int = 5
    box: tuple = ((-0.8, 0.8), (-0.8, 0.8), (0.6, 1.3))
    speed: float = 0.5
    seed: int = 0
    duration_s: float = field(init=False, default=0.0)  # follows from the path

    def __post_init__(self):
        from scipy.interpolate import CubicSpline  # scipy.interpolate costs ~1 s to import: on first use

        rng = np.random.default_rng(self.seed)
        low, high = np.array(self.box, float).T
        self.points = low + (high - low) * rng.random((self.count, 3))
        knots = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))] / self.speed
        self.duration_s = float(knots[-1] + self.ramp_s)
        self._spline = CubicSpline(knots, self.points, bc_type="clamped")

    def path(self, s):
        """(p, dp/ds, d²p/ds²) at nominal times s, each (N, 3): m, m/s, m/s²."""
        s = np.asarray(s, float)
        return self._spline(s), self._spline(s, 1), self._spline(s, 2)


# -- the reference over the whole flight -------------------------------------------------------------------
@dataclass
class Timing:
    """Durations of the phases around the trajectory, s.

    Attributes
    ----------
    sit_before_s : float
        On the ground before take-off, s.
    takeoff_s : float
        Minimum-jerk climb from the ground below the trajectory's first point to that point, s.
    hover_s : float
        Hover before the trajectory and again after it, s (each).
    land_s : float
        Minimum-jerk descent from the trajectory's last point to the ground below it, s.
    sit_after_s : float
        On the ground after touchdown, s.
    """
    sit_before_s: float = 1.5
    takeoff_s: float = 2.0
    hover_s: float = 0.5
    land_s: float = 2.0
    sit_after_s: float = 1.0


@dataclass
class Phases:
    """Simulation times (s) where the flight's phases begin."""
    takeoff: float
    fly: float          # the trajectory starts (speed ramps up)
    fly_end: float      # the trajectory ends (speed back to 0)
    land: float
    touchdown: float    # the landing reference reaches the ground; motors off
    end: float


@dataclass
class Reference:
    """The reference over the whole flight, on the 1 kHz simulation grid.

    Attributes
    ----------
    t : (N,) array
        Simulation time, s.
    p, v, a : (N, 3) arrays
        Position (m), velocity (m/s) and acceleration (m/s²), world frame.
    yaw : (N,) array
        Yaw, rad.
    """
    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: np.ndarray


def reference(trajectory: Trajectory, timing: Timing, yaw_rad: float, yaw_rate: float):
    """(Reference on the 1 kHz grid, Phases).  Yaw: yaw_rad + yaw_rate · s along the trajectory."""
    fly = timing.sit_before_s + timing.takeoff_s + timing.hover_s
    land = fly + trajectory.duration_s + timing.hover_s
    phases = Phases(takeoff=timing.sit_before_s, fly=fly, fly_end=fly + trajectory.duration_s, land=land,
                    touchdown=land + timing.land_s, end=land + timing.land_s + timing.sit_after_s)
    t = np.arange(int(round(phases.end * SIM_RATE_HZ)) + 1) / SIM_RATE_HZ

    first, last = trajectory.path(np.array([0.0, trajectory.s_end]))[0]
    ground_first, ground_last = first * [1, 1, 0], last * [1, 1, 0]
    p, v, a = (np.zeros((len(t), 3)) for _ in range(3))
    rising, flying, landing = t < phases.fly, (t >= phases.fly) & (t < phases.land), t >= phases.land
    for mask, values in ((rising, _minimum_jerk(t[rising] - phases.takeoff, ground_first, first, timing.takeoff_s)),
                         (flying, trajectory.flown(t[flying] - phases.fly)[:3]),
                         (landing, _minimum_jerk(t[landing] - phases.land, last, ground_last, timing.land_s))):
        p[mask], v[mask], a[mask] = values
    s = trajectory.flown(t - phases.fly)[3]
    return Reference(t, p, v, a, yaw_rad + yaw_rate * s), phases

