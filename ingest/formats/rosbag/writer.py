"""ROS bags of a flight written with rosbags (for the simulator and the tests): ROS 2 bags with sqlite3 or
MCAP storage, and ROS 1 bags, with the message types the reader knows, built from the real definitions
(rosbags' standard type stores plus NamedPoseArray / LogDataGeneric from their .msg text)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from learnest.errors import InvalidInput

from ...frames import GRAVITY
from ..mcap.schemas import EXTRA_TYPES, MSG_TEXT

DEFAULT_START_NS = 1_700_000_000 * 10**9     # an epoch time, like a real bag
STORAGES = ("sqlite3", "mcap", "ros1")
POSE_TYPES = {"PoseStamped": "geometry_msgs/msg/PoseStamped", "TransformStamped": "geometry_msgs/msg/TransformStamped",
              "PoseWithCovarianceStamped": "geometry_msgs/msg/PoseWithCovarianceStamped",
              "Odometry": "nav_msgs/msg/Odometry"}


def _typestore(ros1: bool):
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types: dict = {}
    # ROS 1 Noetic's store has no tf2_msgs: its TFMessage is the same list of TransformStamped
    for name in (*EXTRA_TYPES, *(("tf2_msgs/msg/TFMessage",) if ros1 else ())):
        types.update(get_types_from_msg(MSG_TEXT[name], name))
    store.register(types)
    return store


class BagWriter:
    """A bag of pose, multi-body pose, IMU and (ROS 2) LogDataGeneric streams; messages are written in
    receive-time order on close.

    Parameters
    ----------
    path : str or Path
        ROS 1: the .bag file.  ROS 2: the bag folder to create (must not exist); `storage_file` is the .db3 or
        .mcap inside it.
    storage : {"sqlite3", "mcap", "ros1"}
    start_ns : int
        Epoch time of t = 0, ns.
    """

    def __init__(self, path, storage: str = "sqlite3", *, start_ns: int = DEFAULT_START_NS):
        if storage not in STORAGES:
            raise InvalidInput(f"storage must be one of {STORAGES}, not {storage!r}")
        self.path, self.storage, self.start_ns = Path(path), storage, start_ns
        self.store = _typestore(storage == "ros1")
        self.pending: list[tuple[int, int, str, str, object]] = []   # (receive ns, order, topic, type, message)

    # -- message parts ----------------------------------------------------------------------------------
    def _type(self, name: str):
        return self.store.types[name]

    def _header(self, stamp_ns: int, frame_id: str):
        time = self._type("builtin_interfaces/msg/Time")(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if self.storage == "ros1":
            return self._type("std_msgs/msg/Header")(seq=0, stamp=time, frame_id=frame_id)
        return self._type("std_msgs/msg/Header")(stamp=time, frame_id=frame_id)

    def _vector(self, name: str, v):
        return self._type(name)(x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _quaternion(self, q):
        return self._type("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                                          w=float(q[3]))

    def _pose(self, p, q):
        return self._type("geometry_msgs/msg/Pose")(position=self._vector("geometry_msgs/msg/Point", p),
                                                    orientation=self._quaternion(q))

    def _transform(self, stamp_ns: int, parent: str, child: str, p, q):
        transform = self._type("geometry_msgs/msg/Transform")(
            translation=self._vector("geometry_msgs/msg/Vector3", p), rotation=self._quaternion(q))
        return self._type("geometry_msgs/msg/TransformStamped")(header=self._header(stamp_ns, parent),
                                                                child_frame_id=child, transform=transform)

    def _stamp(self, t: float) -> int:
        return self.start_ns + int(round(float(t) * 1e9))

    def _add(self, topic: str, type_name: str, t, log_t, make) -> None:
        log_t = t if log_t is None else log_t
        for i, (sample_t, receive_t) in enumerate(zip(t, log_t)):
            self.pending.append((self._stamp(receive_t), len(self.pending), topic, type_name,
                                 make(i, self._stamp(sample_t))))

    # -- streams ---------------------------------------------------------------------------------------
    def add_pose(self, topic: str, t, p, quat_xyzw, *, message_type: str = "PoseStamped", frame_id: str = "world",
                 child_frame_id: str = "cf1", log_t=None) -> None:
        """One body's poses: t (N,) s from start_ns, p (N, 3) m, quat_xyzw (N, 4); message_type one of
        POSE_TYPES (Odometry gets zero twist, covariances zero)."""
        p, q = np.asarray(p, float), np.asarray(quat_xyzw, float)
        type_name = POSE_TYPES[message_type]

        def make(i, stamp_ns):
            if message_type == "PoseStamped":
                return self._type(type_name)(header=self._header(stamp_ns, frame_id), pose=self._pose(p[i], q[i]))
            if message_type == "TransformStamped":
                return self._transform(stamp_ns, frame_id, child_frame_id, p[i], q[i])
            with_covariance = self._type("geometry_msgs/msg/PoseWithCovariance")(pose=self._pose(p[i], q[i]),
                                                                                covariance=np.zeros(36))
            if message_type == "PoseWithCovarianceStamped":
                return self._type(type_name)(header=self._header(stamp_ns, frame_id), pose=with_covariance)
            zero = self._vector("geometry_msgs/msg/Vector3", (0.0, 0.0, 0.0))
            twist = self._type("geometry_msgs/msg/TwistWithCovariance")(
                twist=self._type("geometry_msgs/msg/Twist")(linear=zero, angular=zero), covariance=np.zeros(36))
            return self._type(type_name)(header=self._header(stamp_ns, frame_id), child_frame_id=child_frame_id,
                                         pose=with_covariance, twist=twist)
        self._add(topic, type_name, t, log_t, make)

    def add_bodies(self, topic: str, t, bodies: dict, *, message_type: str = "NamedPoseArray",
                   frame_id: str = "world", log_t=None) -> None:
        """Several bodies' poses in one message per time: bodies = {name: (p (N, 3), quat_xyzw (N, 4))};
        message_type "NamedPoseArray" (motion_capture_tracking's /poses) or "TFMessage" (/tf, parent frame_id)."""
        arrays = {name: (np.asarray(p, float), np.asarray(q, float)) for name, (p, q) in bodies.items()}
        if message_type == "NamedPoseArray":
            type_name = "motion_capture_tracking_interfaces/msg/NamedPoseArray"

            def make(i, stamp_ns):
                named = [self._type("motion_capture_tracking_interfaces/msg/NamedPose")(name=name,
                                                                                       pose=self._pose(p[i], q[i]))
                         for name, (p, q) in arrays.items()]
                return self._type(type_name)(header=self._header(stamp_ns, frame_id), poses=named)
        elif message_type == "TFMessage":
            type_name = "tf2_msgs/msg/TFMessage"

            def make(i, stamp_ns):
                return self._type(type_name)(transforms=[self._transform(stamp_ns, frame_id, name, p[i], q[i])
                                                         for name, (p, q) in arrays.items()])
        else:
            raise InvalidInput(f"message_type must be NamedPoseArray or TFMessage, not {message_type!r}")
        self._add(topic, type_name, t, log_t, make)

    def add_imu(self, topic: str, t, acc_body_g, *, gyro_rad_s=None, frame_id: str = "cf1", log_t=None) -> None:
        """sensor_msgs/Imu with linear_acceleration = acc_body_g (N, 3) · g in m/s² and angular_velocity =
        gyro_rad_s (N, 3) when given; no orientation (covariance -1), nor angular velocity without gyro_rad_s."""
        acc = np.asarray(acc_body_g, float) * GRAVITY
        gyro = None if gyro_rad_s is None else np.asarray(gyro_rad_s, float)
        not_provided = np.array([-1.0] + [0.0] * 8)
        type_name = "sensor_msgs/msg/Imu"

        def make(i, stamp_ns):
            rate, rate_cov = ((0, 0, 0), not_provided) if gyro is None else (gyro[i], np.zeros(9))
            return self._type(type_name)(
                header=self._header(stamp_ns, frame_id), orientation=self._quaternion((0, 0, 0, 1)),
                orientation_covariance=not_provided,
                angular_velocity=self._vector("geometry_msgs/msg/Vector3", rate),
                angular_velocity_covariance=rate_cov,
                linear_acceleration=self._vector("geometry_msgs/msg/Vector3", acc[i]),
                linear_acceleration_covariance=np.zeros(9))
        self._add(topic, type_name, t, log_t, make)

    def add_log_data(self, topic: str, t, values, *, frame_id: str = "cf1", log_t=None,
                     boot_offset_s: float = 12.0) -> None:
        """crazyflie_interfaces/LogDataGeneric rows, values (N, k) in log-block order (crazyswarm2's custom
        topics; ROS 2 only); `timestamp` is ms since the Crazyflie booted, boot_offset_s before t = 0."""
        if self.storage == "ros1":
            raise InvalidInput("LogDataGeneric is a ROS 2 type (crazyswarm2); a ROS 1 bag cannot carry it")
        values = np.asarray(values, float).reshape(len(t), -1)
        type_name = "crazyflie_interfaces/msg/LogDataGeneric"

        def make(i, stamp_ns):
            return self._type(type_name)(header=self._header(stamp_ns, frame_id),
                                         timestamp=int(round((t[i] + boot_offset_s) * 1000)), values=values[i])
        self._add(topic, type_name, t, log_t, make)

    # -- writing ---------------------------------------------------------------------------------------
    @property
    def storage_file(self) -> Path:
        """The file a reader is given: the .bag, or the .db3 / .mcap inside the ROS 2 bag folder."""
        if self.storage == "ros1":
            return self.path
        return self.path / f"{self.path.name}.{'db3' if self.storage == 'sqlite3' else 'mcap'}"

    def close(self) -> Path:
        """Write the bag; returns `storage_file`."""
        ordered = sorted(self.pending, key=lambda item: item[:2])
        if self.storage == "ros1":
            from rosbags.rosbag1 import Writer as Writer1

            with Writer1(self.path) as bag:
                connections: dict = {}
                for receive_ns, _, topic, type_name, message in ordered:
                    if topic not in connections:
                        connections[topic] = bag.add_connection(topic, type_name, typestore=self.store)
                    bag.write(connections[topic], receive_ns, self.store.serialize_ros1(message, type_name))
            return self.storage_file
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.SQLITE3 if self.storage == "sqlite3" else StoragePlugin.MCAP
        with Writer2(self.path, version=9, storage_plugin=plugin) as bag:
            connections = {}
            for receive_ns, _, topic, type_name, message in ordered:
                if topic not in connections:
                    connections[topic] = bag.add_connection(topic, type_name, typestore=self.store)
                bag.write(connections[topic], receive_ns, self.store.serialize_cdr(message, type_name))
        return self.storage_file

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        if exc_info[0] is None:
            self.close()
