"""Writing a SimulatedFlight in every supported format (`write_flight`), each on its own clock, and mapping
a Flight read back from those files onto simulation time (`sim_times`)."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from learnest.errors import InvalidInput

from ..flight import Flight
from ..formats.crazyflie_usd import writer as usd_writer
from ..formats.mcap import writer as mcap_writer
from ..formats.nanobench import writer as nanobench_writer
from ..formats.vicon_cfclient.writer import write_cfclient_csv, write_vicon_csv
from .sensors import Imu, sample_times
from .simulation import SimulatedFlight

# Where simulation time 0 lies on each file's own clock (see sim_times).
NANOBENCH_EPOCH_S = 1_700_000_000.0     # NanoBench stamps rows with Unix time
USD_BOOT_S = 23.456                     # uSD stamps: time since the Crazyflie booted
CFCLIENT_BOOT_S = 41.237                # cfclient Timestamp: ms since boot (another boot than the uSD one)
VICON_START_S = 0.2                     # the Vicon capture starts 0.2 s after the cfclient log
# The pair's two clocks: t_vicon = t_cfclient + CFCLIENT_CLOCK_OFFSET_S (t_cfclient = Timestamp / 1000).
CFCLIENT_CLOCK_OFFSET_S = -(CFCLIENT_BOOT_S + VICON_START_S)
CFCLIENT_RATE_HZ = 100.0                # a cfclient log block runs at ≤ 100 Hz over the radio
# The mocap pose the vehicle received, as the firmware logs it (position m, quaternion scalar last).
LOCSRV_POSE = ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")

FORMATS = ("nanobench", "usd", "usd-v1", "vicon+cfclient", "cfclient", "mcap-ros2", "mcap-json")
SOURCE_TIME_AT_SIM_ZERO = {"nanobench": NANOBENCH_EPOCH_S, "usd": USD_BOOT_S, "usd-v1": USD_BOOT_S,
                           "vicon+cfclient": -VICON_START_S, "cfclient": CFCLIENT_BOOT_S, "mcap-ros2": 0.0,
                           "mcap-json": 0.0}


def _on_times(t_from, values, t_to) -> np.ndarray:
    return np.column_stack([np.interp(t_to, t_from, values[:, j]) for j in range(values.shape[1])])


def _decimated(imu: Imu, rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, acc_g, gyro, setpoint) at rate_hz: every n-th sample when the IMU rate is a multiple, as a
    log block samples the current value; otherwise interpolated."""
    ratio = (len(imu.t) - 1) / (imu.t[-1] * rate_hz)
    if abs(ratio - round(ratio)) < 1e-9 and round(ratio) >= 1:
        pick = slice(None, None, int(round(ratio)))
        return imu.t[pick], imu.acc_g[pick], imu.gyro[pick], imu.setpoint[pick]
    t = sample_times(imu.t[-1], rate_hz)
    return t, _on_times(imu.t, imu.acc_g, t), _on_times(imu.t, imu.gyro, t), _on_times(imu.t, imu.setpoint, t)


def _write_nanobench(sim: SimulatedFlight, path: Path) -> list[Path]:
    # The NanoBench recorder resampled every onboard stream onto the Vicon stamps by linear interpolation.
    t = sim.mocap.t
    nanobench_writer.write(path, NANOBENCH_EPOCH_S + t, sim.mocap.p, sim.mocap.quat,
                           _on_times(sim.imu.t, sim.imu.acc_g, t), gyro=_on_times(sim.imu.t, sim.imu.gyro, t),
                           setpoint=_on_times(sim.imu.t, sim.imu.setpoint, t))
    return [path]


def _write_usd(sim: SimulatedFlight, path: Path, version: int, pose_stream: str) -> list[Path]:
    """The firmware's layout: a fixed-frequency stream at the IMU rate with acc (g), gyro (deg/s) and the
    setpoint (ctrltargetZ, int16 mm); the mocap pose (locSrv) either sample-and-hold inside it (what real
    logs hold) or in its own event stream at the mocap frames ("event")."""
    imu, mocap = sim.imu, sim.mocap
    fixed = {f"acc.{axis}": ("f", imu.acc_g[:, j]) for j, axis in enumerate("xyz")}
    fixed.update({f"gyro.{axis}": ("f", np.degrees(imu.gyro[:, j])) for j, axis in enumerate("xyz")})
    fixed.update({f"ctrltargetZ.{axis}": ("h", 1000 * imu.setpoint[:, j]) for j, axis in enumerate("xyz")})
    pose = np.column_stack([mocap.p, mocap.quat])
    names = LOCSRV_POSE
    events = {"fixedFrequency": {"t": USD_BOOT_S + imu.t, "vars": fixed}}
    if pose_stream == "fixed":
        latest = np.searchsorted(mocap.t, imu.t + 1e-9, side="right") - 1     # the last frame received
        fixed.update({name: ("f", pose[latest, j]) for j, name in enumerate(names)})
    elif pose_stream == "event":
        pose_vars = {name: ("f", pose[:, j]) for j, name in enumerate(names)}
        events["locSrvPose"] = {"t": USD_BOOT_S + mocap.t, "vars": pose_vars}
    else:
        raise InvalidInput(f"usd pose_stream must be 'fixed' or 'event', not {pose_stream!r}")
    usd_writer.write(path, events, version=version)
    return [path]


def _write_vicon_cfclient(sim: SimulatedFlight, vicon_path: Path, cfclient_path: Path) -> list[Path]:
    """Two clocks: the Vicon export counts from its first frame (VICON_START_S after the cfclient log
    began), the cfclient log stamps ms since boot (CFCLIENT_BOOT_S at simulation time 0)."""
    mocap = sim.mocap
    seen = mocap.t >= VICON_START_S - 1e-9
    write_vicon_csv(vicon_path, mocap.t[seen] - VICON_START_S, mocap.p[seen], mocap.quat[seen],
                    rate_hz=sim.sensors.mocap_rate_hz, units="mm")
    t, acc, gyro, setpoint = _decimated(sim.imu, CFCLIENT_RATE_HZ)
    extra = {f"gyro.{axis}": np.degrees(gyro[:, j]) for j, axis in enumerate("xyz")}
    extra.update({f"ctrltarget.{axis}": setpoint[:, j] for j, axis in enumerate("xyz")})
    write_cfclient_csv(cfclient_path, CFCLIENT_BOOT_S + t, acc, extra)
    return [vicon_path, cfclient_path]


def _write_cfclient_with_pose(sim: SimulatedFlight, path: Path) -> list[Path]:
    """A cfclient "Log to file" CSV that carries the received mocap pose (locSrv.*: the last frame received at
    each log row) next to acc.*, gyro.* and the setpoint: a flight of its own, on the Crazyflie's clock."""
    mocap = sim.mocap
    t, acc, gyro, setpoint = _decimated(sim.imu, CFCLIENT_RATE_HZ)
    latest = np.searchsorted(mocap.t, t + 1e-9, side="right") - 1     # the last frame received
    pose = np.column_stack([mocap.p, mocap.quat])[latest]
    extra = {name: pose[:, j] for j, name in enumerate(LOCSRV_POSE)}
    extra.update({f"gyro.{axis}": np.degrees(gyro[:, j]) for j, axis in enumerate("xyz")})
    extra.update({f"ctrltarget.{axis}": setpoint[:, j] for j, axis in enumerate("xyz")})
    write_cfclient_csv(path, CFCLIENT_BOOT_S + t, acc, extra)
    return [path]


def write_flight(sim: SimulatedFlight, fmt: str, directory, stem: str, *, usd_pose_stream: str = "fixed") -> list[Path]:
    """Write one simulated flight in format `fmt` (see FORMATS) into directory; returns the files to give to
    ingest.read_flights (the Vicon export first for "vicon+cfclient")."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if fmt == "nanobench":
        return _write_nanobench(sim, directory / f"{stem}.csv")
    if fmt in ("usd", "usd-v1"):
        return _write_usd(sim, directory / stem, 2 if fmt == "usd" else 1, usd_pose_stream)
    if fmt == "vicon+cfclient":
        return _write_vicon_cfclient(sim, directory / f"{stem}_vicon.csv", directory / f"{stem}_cfclient.csv")
    if fmt == "cfclient":
        return _write_cfclient_with_pose(sim, directory / f"{stem}_cfclient.csv")
    if fmt in ("mcap-ros2", "mcap-json"):
        path = directory / f"{stem}.mcap"
        writer = mcap_writer.write_ros2 if fmt == "mcap-ros2" else mcap_writer.write_json
        writer(path, sim.mocap.t, sim.mocap.p, sim.mocap.quat, sim.imu.acc_g, t_acc=sim.imu.t)
        return [path]
    raise InvalidInput(f"unknown format {fmt!r} (one of {', '.join(FORMATS)})")


def sim_times(flight: Flight, fmt: str) -> np.ndarray:
    """Simulation time of every row of a Flight read back from a file that write_flight wrote in `fmt`.

    The Flight's t restarts at 0 where its grid starts (meta t0_source_s, on the file's clock) plus the
    take-off cut; each format puts simulation time 0 at SOURCE_TIME_AT_SIM_ZERO[fmt] on that clock (for
    vicon+cfclient, the Vicon clock, on which the Flight lives)."""
    start = flight.meta.get("flying_window", {}).get("start_s", 0.0)
    return flight.t + (flight.meta["t0_source_s"] - SOURCE_TIME_AT_SIM_ZERO[fmt]) + start


# -- a canonical Flight (any source, e.g. models.crazyflie.simulate_crazyflie) written back as a log ---------------
# The firmware variables each Flight channel is written as in the uSD and cfclient logs (the first source of
# ingest.formats.crazyflie_variables.OPTIONAL_SOURCES, in the firmware's own units), with the uSD value type.
FIRMWARE_VARIABLES: dict[str, tuple[tuple[str, ...], str, Callable[[np.ndarray], np.ndarray]]] = {
    "gyro": (("gyro.x", "gyro.y", "gyro.z"), "f", np.degrees),                      # deg/s
    "motors": (("motor.m1", "motor.m2", "motor.m3", "motor.m4"), "I", lambda x: x),  # PWM 0..65535, uint32
    "vbat": (("pm.vbat",), "f", lambda x: x),                                        # V
    "setpoint": (("ctrltarget.x", "ctrltarget.y", "ctrltarget.z"), "f", lambda x: x),  # m
}
CANONICAL_FORMATS = ("nanobench", "usd", "usd-v1", "vicon+cfclient", "mcap-ros2")
ROBOT = "cf1"   # the crazyswarm2 robot name of the ROS 2 recording: its topics are /cf1/...


def _acc_body_g(flight: Flight) -> np.ndarray:
    """The body-frame accelerometer (g): the channel when the Flight has it, else from a_meas and the attitude."""
    from ..frames import GRAVITY, quat_to_matrix

    if "acc_body" in flight.channels:
        return np.asarray(flight.channels["acc_body"], float) / GRAVITY
    world = flight.a_meas + np.array([0.0, 0.0, GRAVITY])
    return np.einsum("tji,tj->ti", quat_to_matrix(flight.quat), world) / GRAVITY


def _firmware_columns(flight: Flight) -> dict:
    """{"group.name": (uSD type code, values in firmware units)} of the channels the Flight carries."""
    columns = {}
    for channel, (names, code, to_firmware) in FIRMWARE_VARIABLES.items():
        if channel in flight.channels:
            values = np.asarray(to_firmware(np.asarray(flight.channels[channel], dtype=float)), dtype=float)
            values = values.reshape(len(flight.t), -1)
            columns.update({name: (code, values[:, j]) for j, name in enumerate(names)})
    return columns


def _write_canonical_ros2(flight: Flight, path: Path, acc_g: np.ndarray) -> list[Path]:
    """A ROS 2 MCAP bag as crazyswarm2 records one: the mocap pose (PoseStamped), the IMU (sensor_msgs/Imu) and
    one LogDataGeneric custom topic /cf1/<channel> per input the Flight carries (FIRMWARE_VARIABLES, firmware
    units), with the crazyflies.yaml that declares those topics beside it (<stem>_crazyflies.yaml)."""
    import yaml

    t = np.asarray(flight.t, float)
    custom_topics = {}
    with mcap_writer.Ros2BagWriter(path) as bag:
        bag.add_pose(f"/mocap/{ROBOT}/pose", t, flight.p, flight.quat)
        bag.add_imu(f"/{ROBOT}/imu", t, acc_g)
        for channel, (names, _, to_firmware) in FIRMWARE_VARIABLES.items():
            if channel in flight.channels:
                values = np.asarray(to_firmware(np.asarray(flight.channels[channel], dtype=float)), dtype=float)
                bag.add_log_data(f"/{ROBOT}/{channel}", t, values.reshape(len(t), -1))
                custom_topics[channel] = {"frequency": int(round(flight.rate_hz)), "vars": list(names)}
    config = {"robots": {ROBOT: {"enabled": True, "type": "cf21"}},
              "all": {"firmware_logging": {"enabled": True, "custom_topics": custom_topics}}}
    path.with_name(f"{path.stem}_crazyflies.yaml").write_text(yaml.safe_dump(config, sort_keys=False))
    return [path]


def write_canonical_flight(flight: Flight, fmt: str, directory, stem: str) -> list[Path]:
    """Write a Flight, with the inputs it carries (motor PWM, battery voltage, gyro, setpoint), as a log.

    Parameters
    ----------
    flight : Flight
        Any Flight on a uniform grid (t in s); the accelerometer is the ``acc_body`` channel (m/s²) when
        present, else ``a_meas`` rotated back into the body frame with gravity added.
    fmt : str
        One of CANONICAL_FORMATS: "nanobench" (CSV, SI units, Unix time), "usd" / "usd-v1" (uSD binary,
        firmware variables, time since boot), "vicon+cfclient" (a Vicon export at the Flight's rate and a
        cfclient log of the onboard variables, on the two clocks `write_flight` uses), "mcap-ros2" (a ROS 2
        MCAP bag as crazyswarm2 records it: pose, sensor_msgs/Imu, one LogDataGeneric topic per input, and the
        ``<stem>_crazyflies.yaml`` that names their variables, which the reader finds beside it); or one of
        MORE_CANONICAL_FORMATS: "cfclient" (a cfclient CSV carrying the received pose, locSrv.*), "mcap-json"
        (pose and accelerometer only), "rosbag-db3" / "rosbag-mcap" (a ROS 2 bag folder with sqlite3 or MCAP
        storage, topics as "mcap-ros2"), "rosbag-ros1" (a ROS 1 .bag: pose and IMU only).  MOTOR_FORMATS carry
        the motor PWM.
    directory, stem : where to write; file names as in `write_flight`.

    Returns
    -------
    list of Path
        The files to give to ``ingest.read_flights`` (the Vicon export first for "vicon+cfclient"; a ROS 2 bag's
        storage file); simulation
        time 0 (the Flight's t = 0) lies at SOURCE_TIME_AT_SIM_ZERO[fmt] on the file's clock.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    t, acc_g = np.asarray(flight.t, float), _acc_body_g(flight)
    if fmt == "nanobench":
        path = directory / f"{stem}.csv"
        given = {name: flight.channels[name] for name in FIRMWARE_VARIABLES if name in flight.channels}
        nanobench_writer.write(path, NANOBENCH_EPOCH_S + t, flight.p, flight.quat, acc_g, **given)
        return [path]
    if fmt in ("usd", "usd-v1"):
        fixed = {f"acc.{axis}": ("f", acc_g[:, j]) for j, axis in enumerate("xyz")}
        fixed.update(_firmware_columns(flight))
        pose = np.column_stack([flight.p, flight.quat])
        fixed.update({name: ("f", pose[:, j]) for j, name in enumerate(LOCSRV_POSE)})
        path = directory / stem
        usd_writer.write(path, {"fixedFrequency": {"t": USD_BOOT_S + t, "vars": fixed}},
                         version=2 if fmt == "usd" else 1)
        return [path]
    if fmt == "vicon+cfclient":
        vicon_path, cfclient_path = directory / f"{stem}_vicon.csv", directory / f"{stem}_cfclient.csv"
        seen = t >= VICON_START_S - 1e-9
        write_vicon_csv(vicon_path, t[seen] - VICON_START_S, flight.p[seen],
                        flight.quat[seen], rate_hz=flight.rate_hz, units="mm")
        extra = {name: values for name, (_, values) in _firmware_columns(flight).items()}
        write_cfclient_csv(cfclient_path, CFCLIENT_BOOT_S + t, acc_g, extra)
        return [vicon_path, cfclient_path]
    if fmt == "mcap-ros2":
        return _write_canonical_ros2(flight, directory / f"{stem}.mcap", acc_g)
    return _write_more_canonical(flight, fmt, directory, stem, acc_g)


# -- the other formats a canonical Flight can be written in ------------------------------------------------
# Written by `write_canonical_flight` beside CANONICAL_FORMATS: a cfclient CSV that carries the pose itself, a
# JSON-encoded MCAP, and ROS bags written with rosbags (ROS 2 with sqlite3 or MCAP storage, ROS 1).
MORE_CANONICAL_FORMATS = ("cfclient", "mcap-json", "rosbag-db3", "rosbag-mcap", "rosbag-ros1")
ALL_CANONICAL_FORMATS = CANONICAL_FORMATS + MORE_CANONICAL_FORMATS
# Those whose files carry the Flight's motor PWM (and its other inputs); the rest carry the pose and the
# accelerometer only: a JSON MCAP has no input channels (the reader takes inputs from LogDataGeneric topics
# only) and a ROS 1 bag cannot hold LogDataGeneric, a ROS 2 type.
MOTOR_FORMATS = ("nanobench", "usd", "usd-v1", "vicon+cfclient", "cfclient", "mcap-ros2", "rosbag-db3",
                 "rosbag-mcap")
SOURCE_TIME_AT_SIM_ZERO.update({"rosbag-db3": 0.0, "rosbag-mcap": 0.0, "rosbag-ros1": 0.0})
ROSBAG_STORAGE = {"rosbag-db3": "sqlite3", "rosbag-mcap": "mcap", "rosbag-ros1": "ros1"}


def _write_canonical_cfclient(flight: Flight, path: Path, acc_g: np.ndarray) -> list[Path]:
    """A cfclient "Log to file" CSV with the pose the vehicle received (locSrv.*) beside acc.* and the inputs
    the Flight carries (firmware units), stamped in ms since boot (CFCLIENT_BOOT_S at the Flight's t = 0)."""
    pose = np.column_stack([flight.p, flight.quat])
    extra = {name: pose[:, j] for j, name in enumerate(LOCSRV_POSE)}
    extra.update({name: values for name, (_, values) in _firmware_columns(flight).items()})
    write_cfclient_csv(path, CFCLIENT_BOOT_S + np.asarray(flight.t, float), acc_g, extra)
    return [path]


def _write_canonical_rosbag(flight: Flight, directory: Path, stem: str, storage: str,
                            acc_g: np.ndarray) -> list[Path]:
    """A ROS bag as crazyswarm2 records one (formats.rosbag.writer): the mocap pose (PoseStamped), the IMU
    (sensor_msgs/Imu) and, in a ROS 2 bag, one LogDataGeneric topic /cf1/<channel> per input the Flight carries
    with the ``<storage file stem>_crazyflies.yaml`` that names their values beside the storage file.  A ROS 2
    bag is the folder ``directory/stem`` (metadata.yaml and the .db3 or .mcap); a ROS 1 bag is ``stem.bag``."""
    import yaml

    from ..formats.rosbag.writer import BagWriter

    t = np.asarray(flight.t, float)
    ros1 = storage == "ros1"
    bag = BagWriter(directory / (f"{stem}.bag" if ros1 else stem), storage)
    bag.add_pose(f"/mocap/{ROBOT}/pose", t, flight.p, flight.quat)
    bag.add_imu(f"/{ROBOT}/imu", t, acc_g)
    custom_topics = {}
    if not ros1:     # LogDataGeneric is a ROS 2 type: a ROS 1 bag carries no inputs
        for channel, (names, _, to_firmware) in FIRMWARE_VARIABLES.items():
            if channel in flight.channels:
                values = np.asarray(to_firmware(np.asarray(flight.channels[channel], dtype=float)), dtype=float)
                bag.add_log_data(f"/{ROBOT}/{channel}", t, values.reshape(len(t), -1))
                custom_topics[channel] = {"frequency": int(round(flight.rate_hz)), "vars": list(names)}
    storage_file = bag.close()
    if custom_topics:
        config = {"robots": {ROBOT: {"enabled": True, "type": "cf21"}},
                  "all": {"firmware_logging": {"enabled": True, "custom_topics": custom_topics}}}
        storage_file.with_name(f"{storage_file.stem}_crazyflies.yaml").write_text(yaml.safe_dump(config,
                                                                                                sort_keys=False))
    return [storage_file]


def _write_more_canonical(flight: Flight, fmt: str, directory: Path, stem: str, acc_g: np.ndarray) -> list[Path]:
    """`write_canonical_flight` for MORE_CANONICAL_FORMATS."""
    if fmt == "cfclient":
        return _write_canonical_cfclient(flight, directory / f"{stem}_cfclient.csv", acc_g)
    if fmt == "mcap-json":
        path = directory / f"{stem}.mcap"
        mcap_writer.write_json(path, np.asarray(flight.t, float), flight.p, flight.quat, acc_g)
        return [path]
    if fmt in ROSBAG_STORAGE:
        return _write_canonical_rosbag(flight, directory, stem, ROSBAG_STORAGE[fmt], acc_g)
    raise InvalidInput(f"unknown format {fmt!r} for a Flight (one of {', '.join(ALL_CANONICAL_FORMATS)})")
