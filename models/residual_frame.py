"""Where the residual Δθ looks and where it acts: its input features and how its output enters ẋ.

Two frames, written once against `models.backend` so the same residual runs in numpy, torch and CasADi:

``"state"`` (the paper's form)
    Δθ reads [x, u] (masked by `System.residual_masks`) and corrects every row of ẋ (masked likewise).
``"body"`` (vehicles with x = [p, v, a] and inputs [q (scalar last), four thrust columns, battery], the
    Crazyflie's `models.crazyflie.INPUT_NAMES`)
    Δθ reads what the physics acts through, in the body frame: the height p_z (ground effect), the body
    velocity Rᵀv (rotor drag), the collective thrust column (the mean of the four) and the battery voltage.
    Its output is a body-frame rate of the specific force, rotated by R(q) into ȧ.  A newly trained body
    residual does not read the velocity along the thrust axis (`UNREAD_BODY_FEATURES`, why there).

Why the body frame: a residual that sees the world velocity and the attitude can tell a counter-clockwise
circle from a clockwise one (the tilt points to the centre, left of the velocity on one, right on the other)
and where the vehicle points.  A residual trained on one turn sense then extrapolates on the other.  The body
frame leaves it nothing to learn but the vehicle: heading, position and the sense of a turn are not among
its inputs, and the force it adds turns with the vehicle.
"""
from __future__ import annotations

from collections.abc import Callable

from learnest.errors import InvalidInput

from .backend import Array, ops_for
from .crazyflie.prior import rotation_columns

FRAMES = ("state", "body")

# the body frame's layout: state [px, py, pz, vx, vy, vz, ax, ay, az], inputs [qx, qy, qz, qw, t1..t4, vbat]
BODY_FEATURES = ("pz", "vbx", "vby", "vbz", "thrust_mean", "vbat")
BODY_OUTPUTS = ("fbx_rate", "fby_rate", "fbz_rate")
_BODY_STATES, _BODY_INPUTS = 9, 9

# Body features no newly trained residual reads: the velocity along the thrust axis, so the vertical rotor drag
# stays the prior's k_z.  Why: the flights do not determine it.  That velocity spreads a few cm/s on hovering and
# circling flights, and the thrust-axis force the prior leaves unexplained slopes against it with opposite signs
# from one trajectory family to the next; a residual reading it learns a drag that does not carry, and an
# estimator crossing a mocap gap takes its vertical velocity from that drag (docs/results/residual-frame.md).
UNREAD_BODY_FEATURES = ("vbz",)


def check_frame(frame: str, n: int | None = None, n_inputs: int | None = None) -> str:
    """``frame`` when it is known (and, for ``"body"``, fits a system of ``n`` states and ``n_inputs`` inputs).

    Raises
    ------
    InvalidInput
        For an unknown frame, or a body frame on a system without the [p, v, a] state and the attitude,
        thrust and battery inputs.
    """
    if frame not in FRAMES:
        raise InvalidInput(f"residual frame must be one of {', '.join(FRAMES)}, not {frame!r}")
    if frame == "body" and n is not None and (n, n_inputs) != (_BODY_STATES, _BODY_INPUTS):
        raise InvalidInput(f"a body-frame residual needs 9 states [p, v, a] and 9 inputs [q, thrust x4, battery]; "
                           f"this system has {n} states and {n_inputs} inputs")
    return frame


def feature_count(frame: str, n: int, n_inputs: int) -> tuple[int, int]:
    """(inputs, outputs) of the network for ``frame`` on a system of ``n`` states and ``n_inputs`` inputs."""
    return (len(BODY_FEATURES), len(BODY_OUTPUTS)) if frame == "body" else (n + n_inputs, n)


def body_input_mask(blind: tuple) -> list[float]:
    """The body frame's input mask (1.0 where Δθ reads) for a system blind to the states and inputs ``blind``
    (`System.residual_blind`): a feature is masked when everything it is made of is, and `UNREAD_BODY_FEATURES`
    always.  The attitude makes the frame itself, so an attitude-blind system's body residual still turns with
    the vehicle."""
    made_of = {"pz": ("pz",), "vbx": ("vx", "vy", "vz"), "vby": ("vx", "vy", "vz"), "vbz": ("vx", "vy", "vz"),
               "thrust_mean": ("pwm1", "pwm2", "pwm3", "pwm4"), "vbat": ("vbat",)}
    return [0.0 if name in UNREAD_BODY_FEATURES or all(k in blind for k in made_of[name]) else 1.0
            for name in BODY_FEATURES]


def features(frame: str, x: Array, u: Array | None) -> Array:
    """The network's input for states ``x`` and inputs ``u`` in ``frame``.

    Parameters
    ----------
    frame : {"state", "body"}
    x : ndarray (..., n), Tensor (..., n) or CasADi (n, 1)
    u : same kind, (..., p) or (p,) held for a batch of states; None or width 0 without inputs

    Returns
    -------
    Same kind: ``"state"`` [x, u] (..., n + p); ``"body"`` (..., 6) in `BODY_FEATURES` order (m, m/s, the
    thrust columns' unit, V).
    """
    return _features(frame, x, u, _rotation(frame, x, u))


def field(frame: str, network: Callable[[Array], Array], x: Array, u: Array | None) -> Array:
    """Δθ(x, u) as a correction of ẋ (shape of ``x``): ``network`` on the frame's features, its output as is in
    the state frame, and in the body frame the rotated force rate R(q)·y in the acceleration rows, zero elsewhere
    (R computed once for both)."""
    R = _rotation(frame, x, u)
    y = network(_features(frame, x, u, R))
    if frame != "body":
        return y
    ops = ops_for(x)
    f = ops.unstack(y)
    zero = ops.zeros_like_first(x)
    world = [R[i][0] * f[0] + R[i][1] * f[1] + R[i][2] * f[2] for i in range(3)]
    return ops.stack([zero] * 6 + world)


def _rotation(frame: str, x: Array, u: Array | None):
    """Rows of R(q) (body -> world) from the inputs' quaternion for the body frame; None for the state frame."""
    if frame != "body":
        return None
    if u is None:
        raise InvalidInput("a body-frame residual needs the inputs: the attitude, the thrust columns and the battery")
    return rotation_columns(*ops_for(x).unstack(u)[:4])


def _features(frame: str, x: Array, u: Array | None, R) -> Array:
    ops = ops_for(x)
    if frame != "body":
        return ops.concat([x, u]) if u is not None and _width(ops, u) else x
    assert u is not None     # `_rotation` refused a body frame without inputs
    s, inputs = ops.unstack(x), ops.unstack(u)
    v = s[3:6]
    body_v = [R[0][j] * v[0] + R[1][j] * v[1] + R[2][j] * v[2] for j in range(3)]   # Rᵀ v
    thrust_mean = (inputs[4] + inputs[5] + inputs[6] + inputs[7]) * 0.25
    zero = ops.zeros_like_first(x)
    return ops.stack([s[2] + zero, *body_v, thrust_mean + zero, inputs[8] + zero])


def _width(ops, u) -> int:
    return int(u.shape[0] if ops.name == "casadi" else u.shape[-1])
