"""The canonical Flight every adapter produces and every later stage consumes.

Uniform time grid (100 Hz default), SI units, world frame z-up, time in seconds from the flight's start.
`a_meas` is the accelerometer's body-frame specific force rotated into the world by the mocap attitude,
with gravity removed (m/s²).  Quaternions are scalar-last [qx, qy, qz, qw].
"""
from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

GRAVITY = 9.80665

REQUIRED = ("t", "p", "a_meas", "quat")
OPTIONAL = ("gyro", "motors", "vbat", "rotor_speed", "thrust_cmd", "thrust_si", "setpoint", "v_onboard",
            "p_onboard", "acc_body")
# The unit every optional channel is stored in, whatever the format wrote (converters: ingest.units).
CHANNEL_UNITS = {
    "gyro": "rad/s, body frame",
    "motors": "PWM duty of motors 1..4 as the firmware logs it, 0..65535 (after battery compensation)",
    "vbat": "V, battery",
    "rotor_speed": "rad/s, rotors 1..4",
    "thrust_cmd": "collective thrust command of the controller, firmware units 0..65535",
    "thrust_si": "collective thrust command, N",
    "setpoint": "m, world frame",
    "v_onboard": "m/s, world frame",
    "p_onboard": "m, world frame",
    "acc_body": "m/s², body frame specific force",
}


class IngestError(ValueError):
    """A file that cannot become a Flight; the message names the file and the problem."""

    def __init__(self, path, problem: str):
        self.path, self.problem = str(path), problem
        super().__init__(f"{path}: {problem}")


@dataclass
class Flight:
    t: np.ndarray                 # (T,) s from the flight's start, uniform
    p: np.ndarray                 # (T, 3) m, mocap position, world z-up
    a_meas: np.ndarray            # (T, 3) m/s², world frame, gravity removed
    quat: np.ndarray              # (T, 4) mocap attitude, scalar last
    channels: dict = field(default_factory=dict)   # optional arrays, each with T rows (see OPTIONAL)
    meta: dict = field(default_factory=dict)       # sources, adapter, rates, clock offset, quality ...

    def __post_init__(self):
        T = len(self.t)
        for name in ("p", "a_meas", "quat"):
            arr = getattr(self, name)
            if len(arr) != T:
                raise ValueError(f"Flight.{name} has {len(arr)} rows but t has {T}")
        for name, arr in self.channels.items():
            if len(arr) != T:
                raise ValueError(f"Flight channel {name!r} has {len(arr)} rows but t has {T}")

    @property
    def rate_hz(self) -> float:
        return 1.0 / self.dt

    @property
    def dt(self) -> float:
        return float(np.median(np.diff(self.t))) if len(self.t) > 1 else float("nan")

    @property
    def duration_s(self) -> float:
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0

    @property
    def name(self) -> str:
        return self.meta.get("name") or Path(self.meta.get("sources", [{"path": "flight"}])[0]["path"]).stem

    @property
    def quality(self) -> dict:
        return self.meta.get("quality", {"ok": True, "issues": []})

    def measurements(self) -> np.ndarray:
        """y = [p, a_meas] (T, 6), the quadrotor's measurement vector (Sec. V-C)."""
        return np.column_stack([self.p, self.a_meas])

    def slice(self, start: int, stop: int) -> "Flight":
        """Rows [start, stop) with time restarted at zero."""
        t = self.t[start:stop]
        return Flight(t - t[0], self.p[start:stop], self.a_meas[start:stop], self.quat[start:stop],
                      {k: v[start:stop] for k, v in self.channels.items()}, dict(self.meta))

    # -- persistence: one .npz, arrays exact, metadata as JSON inside --------------------------------
    def to_bytes(self) -> bytes:
        buffer = io.BytesIO()
        arrays = {"t": self.t, "p": self.p, "a_meas": self.a_meas, "quat": self.quat}
        arrays.update({f"channel__{k}": v for k, v in self.channels.items()})
        np.savez_compressed(buffer, meta=np.frombuffer(json.dumps(self.meta).encode(), dtype=np.uint8), **arrays)
        return buffer.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> "Flight":
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            meta = json.loads(npz["meta"].tobytes().decode())
            channels = {k[len("channel__"):]: npz[k] for k in npz.files if k.startswith("channel__")}
            return cls(npz["t"], npz["p"], npz["a_meas"], npz["quat"], channels, meta)

    def save(self, path) -> None:
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(self.to_bytes())
        tmp.replace(path)  # atomic: never a half-written flight on disk

    @classmethod
    def load(cls, path) -> "Flight":
        try:
            return cls.from_bytes(Path(path).read_bytes())
        except (OSError, ValueError, KeyError) as err:
            raise IngestError(path, f"not a saved learnest flight ({err})") from None



def imu_misalignment(roll: float, pitch: float) -> Rotation:
    """Rotation body <- IMU of an accelerometer mounted tilted by roll (about x), then pitch (about y):
    it reads R⁻¹ f for the body-frame specific force f.  The simulator and the diagnosis share it."""
    return Rotation.from_euler("ZYX", [0.0, pitch, roll])


def sha256_file(path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """(T, 4) scalar-last unit quaternions -> (T, 3, 3) body-to-world rotation matrices."""
    q = np.asarray(quat, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def world_acceleration(acc_body_g: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Body-frame specific force in g -> world-frame acceleration in m/s² with gravity removed."""
    specific_force = np.einsum("tij,tj->ti", quat_to_matrix(quat), np.asarray(acc_body_g) * GRAVITY)
    return specific_force - np.array([0.0, 0.0, GRAVITY])
