"""Where the flight is in a recording, told from every signal the log carries (`find_flight`).

A recording usually holds more than the flight: the vehicle sits on the floor before take-off and after
landing, and may be picked up by hand afterwards.  Height alone cannot tell these apart from flying (a hand
lifts the vehicle as a take-off does; a log that starts hovering has no floor to measure from), so each
signal says what it can:

- **power** (motor PWM ``motors``, rotor speeds ``rotor_speed``, the collective thrust command
  ``thrust_cmd`` or ``thrust_si``): motors off is not flying, whatever the height says.  The flight lies in
  the longest stretch with the motors running; a hand pick-up after landing (motors off) is outside it.
- **accelerometer at rest** (``acc_body``): a vehicle resting on the floor reads 1 g with almost no
  vibration (NanoBench: 0.001 g standard deviation over 1 s at rest, >= 0.003 g in a hover).  Held in a hand
  or flying it is not still; a noisy accelerometer is simply never read as resting.
- **height above the floor**, when a floor is seen: the height of the samples where the vehicle was on the
  ground (motors off and, where the accelerometer can tell, at rest), lowest cluster; take-off is measured
  from where it sat before the motors started, touchdown from where it sits after they stopped.  Within the
  powered stretch the flight is where the vehicle is FLYING_HEIGHT_M above that floor; take-off and
  touchdown transients are trimmed as by the height rule (`ingest.align.flying_window`).

A recording that starts with the motors running above the floor is kept from its first sample; one that
ends with them running in the air is kept to its last.  One whose motors (or rotor speeds) run from its first
to its last sample while the accelerometer never rests never stood on anything: it is kept whole, and the
heights are not asked (a climb is not a take-off, a dip below the starting height in the air not a landing).
A log with neither a power signal nor a resting accelerometer falls back to the height rule alone, and the
reason printed says so.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import uniform_filter1d

from .frames import GRAVITY

# Channels that say whether the motors run, in order of preference, with the name the reason prints.
POWER_CHANNELS = (("motors", "motor PWM"), ("rotor_speed", "rotor speeds"), ("thrust_cmd", "thrust command"),
                  ("thrust_si", "thrust command"))
# Motors are running when the signal exceeds this fraction of its 99th percentile over the recording: units
# differ between channels (PWM 0-65535, rad/s, N), and a spinning-up or idling motor is already well above
# 5 % while a stopped one reads 0.  A channel whose 99th percentile is 0 carries nothing (not logged).
POWER_ON_FRACTION = 0.05
# A motor reading 0 for less than this inside a powered stretch is a logging dropout, not a stop (a
# Crazyflie cannot land, stop and restart in 0.3 s).
POWER_GAP_S = 0.3

# At rest the accelerometer reads |a| = 1 g within 0.05 g (scale error) and its magnitude varies by less
# than REST_STD_G over REST_WINDOW_S.  NanoBench on the floor: 0.001 g; in a hover >= 0.003 g (the uSD
# logs' calmest second in the air: 0.0028 g).  A stretch must be at rest for REST_MIN_S to count.
REST_STD_G = 0.002
REST_LEVEL_G = 0.05
REST_WINDOW_S = 1.0
REST_MIN_S = 1.0

# The floor: the median height of the ground samples within FLOOR_BAND_M of their lowest (a vehicle set
# down on a table or held still in a hand is higher).  Fewer than FLOOR_MIN_S of ground samples: no floor.
FLOOR_BAND_M = 0.05
FLOOR_MIN_S = 0.3


@dataclass
class FlightSpan:
    """The stretch of a recording that is the flight.

    Attributes
    ----------
    start, stop : int
        Sample indices [start, stop) on the recording's grid.
    rule : str
        Why, naming the signals used.
    signals : list of str
        The signals that decided ("motor PWM", "accelerometer at rest", "accelerometer never at rest",
        "height above the floor", "height").
    floor_m : float or None
        The floor's height (m, mocap z) when a floor was seen.
    """
    start: int
    stop: int
    rule: str
    signals: list = field(default_factory=list)
    floor_m: float | None = None


def powered(channels: dict, rate_hz: float) -> tuple[np.ndarray | None, list[str]]:
    """Per sample, whether the motors run, from every power channel the flight has.

    Parameters
    ----------
    channels : dict
        Flight channels on the grid: ``motors`` (T, 4) PWM, ``rotor_speed`` (T, 4) rad/s, ``thrust_cmd`` (T,)
        firmware units, ``thrust_si`` (T,) N (any subset).
    rate_hz : float
        Grid rate, Hz.

    Returns
    -------
    (mask (T,) bool or None, names)
        None when no channel carries a power signal; names of the channels used.
    """
    mask, names = None, []
    for key, label in POWER_CHANNELS:
        values = channels.get(key)
        if values is None:
            continue
        values = np.abs(np.asarray(values, dtype=float).reshape(len(values), -1))
        values = np.where(np.isfinite(values), values, 0.0)
        level = float(np.percentile(values.max(axis=1), 99)) if len(values) else 0.0
        if not level > 0:
            continue                      # logged as zeros throughout: says nothing
        on = values.max(axis=1) > POWER_ON_FRACTION * level
        mask = on if mask is None else mask | on
        if label not in names:
            names.append(label)
    if mask is not None:
        mask = _close_gaps(mask, int(round(POWER_GAP_S * rate_hz)))
    return mask, names


def resting(acc_body: ArrayLike | None, rate_hz: float) -> np.ndarray | None:
    """Per sample, whether the accelerometer says the vehicle rests (1 g, no vibration, for REST_MIN_S).

    ``acc_body`` (T, 3) m/s², body frame (None: no accelerometer).  Returns (T,) bool, or None.
    """
    if acc_body is None:
        return None
    magnitude = np.linalg.norm(np.asarray(acc_body, dtype=float), axis=1) / GRAVITY
    if magnitude.size == 0 or not np.all(np.isfinite(magnitude)):
        return None
    window = max(3, int(round(REST_WINDOW_S * rate_hz)))
    if len(magnitude) < window:
        return np.zeros(len(magnitude), dtype=bool)
    mean = uniform_filter1d(magnitude, window, mode="nearest")
    spread = np.sqrt(np.maximum(uniform_filter1d(magnitude ** 2, window, mode="nearest") - mean ** 2, 0.0))
    still = (spread < REST_STD_G) & (np.abs(mean - 1.0) < REST_LEVEL_G)
    return _long_runs(still, int(round(REST_MIN_S * rate_hz)))


def floor_height(z: np.ndarray, ground: np.ndarray, rate_hz: float) -> float | None:
    """The floor's height (m): median z of the ground samples in the lowest FLOOR_BAND_M; None with fewer
    than FLOOR_MIN_S of ground samples."""
    heights = z[ground & np.isfinite(z)]
    if heights.size < max(2, FLOOR_MIN_S * rate_hz):
        return None
    lowest = float(np.percentile(heights, 1))
    return float(np.median(heights[heights <= lowest + FLOOR_BAND_M]))


def find_flight(t: ArrayLike, p: ArrayLike, rate_hz: float, channels: dict | None = None, *,
                flying_height_m: float, takeoff_settle_s: float, landing_settle_s: float,
                height_rule=None) -> FlightSpan:
    """The flight's span in a recording, from power, accelerometer and height.

    Parameters
    ----------
    t : array_like, shape (T,)
        Grid time, s.
    p : array_like, shape (T, 3)
        Position, m, z up.
    rate_hz : float
        Grid rate, Hz.
    channels : dict, optional
        The flight's channels on the grid (``motors``, ``rotor_speed``, ``thrust_cmd``, ``thrust_si``,
        ``acc_body``), as `ingest.align.build_flight` makes them.
    flying_height_m : float
        Height above the floor that counts as airborne, m.
    takeoff_settle_s, landing_settle_s : float
        Time trimmed after lift-off and before touchdown (the transients), s.
    height_rule : callable, optional
        ``(t, p, rate_hz) -> (start, stop, rule)``: the height-only rule, used when no signal sees the ground.

    Returns
    -------
    FlightSpan
    """
    t, p = np.asarray(t, dtype=float), np.asarray(p, dtype=float)
    channels = channels or {}
    n = len(t)
    z = p[:, 2]
    power, power_names = powered(channels, rate_hz)
    signals = list(power_names)

    rest = resting(channels.get("acc_body"), rate_hz)
    if power is not None and power.all():
        return _powered_throughout(t, p, rate_hz, power_names, rest, height_rule)

    floor, ground = _floor_and_ground(z, power, rest, rate_hz, signals)

    if floor is None:
        return _span_without_a_floor(t, p, rate_hz, signals, height_rule)
    signals.append("height above the floor")

    first, last = 0, n
    if power is not None:
        first, last = _longest_run(power)
    # take-off is measured from where the vehicle sat before, touchdown where it sits after (a pad, another
    # spot of an uneven floor): the floor of each side when that side has ground samples of its own
    before, after = floor_height(z[:first], ground[:first], rate_hz), floor_height(z[last:], ground[last:], rate_hz)
    floor_in = floor if before is None else before   # 0.000 m is a floor: only None means no ground samples
    floor_out = floor if after is None else after
    rising = np.flatnonzero(z[first:last] > floor_in + flying_height_m) + first
    falling = np.flatnonzero(z[first:last] > floor_out + flying_height_m) + first
    used = ", ".join(signals)
    if rising.size == 0 or falling.size == 0:
        what = "while the motors ran: the powered stretch" if power is not None else ": the whole recording"
        return FlightSpan(first, last, f"never {flying_height_m:g} m above the floor {what} kept ({used})",
                          signals, floor)
    airborne = np.array([rising[0], falling[-1]])
    settle_in, settle_out = int(round(takeoff_settle_s * rate_hz)), int(round(landing_settle_s * rate_hz))
    starts_in_air = first == 0 and rising[0] == 0
    ends_in_air = last == n and falling[-1] == n - 1
    start = 0 if starts_in_air else int(airborne[0]) + settle_in
    stop = n if ends_in_air else int(airborne[-1]) + 1 - settle_out
    if stop <= start:
        return FlightSpan(int(airborne[0]), max(int(airborne[-1]), int(airborne[0])) + 1,
                          f"airborne too briefly to trim: airborne part kept ({used})", signals, floor)
    motors = "with the motors running " if power is not None else ""
    head = ("from the start (the log starts in the air: " + motors + f"{z[0] - floor_in:.2f} m above the floor)"
            if starts_in_air else
            f"{takeoff_settle_s:g} s after first rising {flying_height_m:g} m above the floor {motors}".rstrip())
    tail = ("to the end (the log ends in the air)" if ends_in_air else
            f"to {landing_settle_s:g} s before last coming down below it")
    if power is not None and last < n and not ends_in_air:
        tail += f"; the motors stop at {t[last - 1] - t[0]:.2f} s"
    return FlightSpan(int(start), int(stop), f"kept {head} {tail} ({used}; floor at {floor:.3f} m)",
                      signals, floor)


# -- helpers ---------------------------------------------------------------------------------------------
def _span_without_a_floor(t: np.ndarray, p: np.ndarray, rate_hz: float, signals: list, height_rule) -> FlightSpan:
    """No signal saw the vehicle on the ground: the height-only rule where one is given, else all of it."""
    if height_rule is None:
        return FlightSpan(0, len(t), "whole recording kept: no signal saw the vehicle on the ground", signals)
    start, stop, rule = height_rule(t, p, rate_hz)
    return FlightSpan(start, stop, f"{rule} (from the height alone: no signal saw the vehicle on the ground)",
                      ["height"])


def _powered_throughout(t: np.ndarray, p: np.ndarray, rate_hz: float, power_names: list, rest: np.ndarray | None,
                        height_rule) -> FlightSpan:
    """`find_flight` when the motors run from the first to the last sample: no ground time with the motors off.

    With an accelerometer that never rests as well, the vehicle never stood on anything (not on the floor,
    not idling on a pad): airborne throughout, the whole recording is kept and the heights are not asked (a
    climb is not a take-off, a dip below the starting height not a landing).  Only a resting accelerometer
    (motors idling on the floor at an end) leaves the ends to the height rule; without an accelerometer too.
    """
    n, power = len(t), ", ".join(power_names)
    if rest is not None and not rest.any():
        return FlightSpan(0, n, f"whole recording kept: airborne throughout (the motors run from its first to its "
                                f"last sample ({power}) and the accelerometer never rests: it never stood on "
                                f"anything)", power_names + ["accelerometer never at rest"])
    if rest is None:
        why = f"the motors run from the first to the last sample: {power}; no accelerometer to tell a rest"
    else:
        resting_s = np.flatnonzero(rest)[[0, -1]] / rate_hz
        why = (f"the motors run from the first to the last sample: {power}; the accelerometer rests at "
               f"{resting_s[0]:.2f}-{resting_s[1]:.2f} s")
    signals = power_names + ([] if rest is None else ["accelerometer at rest"]) + ["height"]
    if height_rule is None:
        return FlightSpan(0, n, f"whole recording kept ({why})", signals)
    start, stop, rule = height_rule(t, p, rate_hz)
    if (start, stop) == (0, n):
        rule = "whole recording kept: the heights show no take-off from a floor and no landing"
    return FlightSpan(start, stop, f"{rule} ({why}; the heights tell where it stood)", signals)


def _floor_and_ground(z: np.ndarray, power: np.ndarray | None, rest: np.ndarray | None, rate_hz: float,
                      signals: list) -> tuple[float | None, np.ndarray]:
    """The floor height (m, None when no signal sees the vehicle on the ground) and the ground samples (T,)
    bool: motors off, narrowed to where the accelerometer rests when it can tell (a hand holding the
    vehicle with the motors off is not the floor); without a power signal, the resting accelerometer alone.
    Appends to ``signals`` the accelerometer when it decided."""
    ground = ~power if power is not None else np.zeros(len(z), dtype=bool)
    floor = None
    if rest is not None:
        still = rest & ground if power is not None else rest
        floor = floor_height(z, still, rate_hz)
        if floor is not None and floor > np.percentile(z[np.isfinite(z)], 1) + FLOOR_BAND_M:
            floor = None   # still, but above the lowest the vehicle ever was: a calm hover, not the floor
        if floor is not None:
            signals.append("accelerometer at rest")
            ground = still
    if floor is None and power is not None:
        floor = floor_height(z, ground, rate_hz)    # the lowest cluster of the motors-off samples
    return floor, ground


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _close_gaps(mask: np.ndarray, shortest: int) -> np.ndarray:
    """Off-runs shorter than ``shortest`` samples between two on-runs become on."""
    out = mask.copy()
    for start, stop in _runs(~mask):
        if start > 0 and stop < len(mask) and stop - start < shortest:
            out[start:stop] = True
    return out


def _long_runs(mask: np.ndarray, shortest: int) -> np.ndarray:
    out = np.zeros_like(mask)
    for start, stop in _runs(mask):
        if stop - start >= shortest:
            out[start:stop] = True
    return out


def _longest_run(mask: np.ndarray) -> tuple[int, int]:
    runs = _runs(mask)
    return max(runs, key=lambda run: run[1] - run[0]) if runs else (0, len(mask))
