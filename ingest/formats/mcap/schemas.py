"""The message types an MCAP recording's pose and acceleration come in: ROS 2 message definitions
(concatenated "ros2msg" text, as rosbag2 stores them) and JSON schemas (Foxglove's and learnest's), and
which schema names may carry a pose or an acceleration at all."""
from __future__ import annotations

# -- ROS 2 message definitions (concatenated "ros2msg" text, as rosbag2 stores them) ----------------------

ROS2MSG_SEPARATOR = "=" * 80
MSG_TEXT = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "sensor_msgs/msg/Imu": ("std_msgs/Header header\n"
                            "geometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
                            "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
                            "geometry_msgs/Vector3 linear_acceleration\n"
                            "float64[9] linear_acceleration_covariance"),
    # crazyswarm2's definition (timestamp: uint32 ms since boot).  Some releases use float32[] values;
    # the reader decodes whatever definition the file carries.
    "crazyflie_interfaces/msg/LogDataGeneric": "std_msgs/Header header\nuint32 timestamp\nfloat64[] values",
}
MSG_DEPENDENCIES = {
    "std_msgs/msg/Header": ["builtin_interfaces/msg/Time"],
    "geometry_msgs/msg/Pose": ["geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion"],
    "geometry_msgs/msg/Transform": ["geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion"],
    "geometry_msgs/msg/PoseStamped": ["std_msgs/msg/Header", "geometry_msgs/msg/Pose"],
    "geometry_msgs/msg/TransformStamped": ["std_msgs/msg/Header", "geometry_msgs/msg/Transform"],
    "sensor_msgs/msg/Imu": ["std_msgs/msg/Header", "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Vector3"],
    "crazyflie_interfaces/msg/LogDataGeneric": ["std_msgs/msg/Header"],
}


def _all_dependencies(type_name: str) -> list[str]:
    """Every type `type_name` uses, depth first, each once (rosbag2's order)."""
    found: list[str] = []
    for dependency in MSG_DEPENDENCIES.get(type_name, []):
        for name in [dependency, *_all_dependencies(dependency)]:
            if name not in found:
                found.append(name)
    return found


def ros2msg_definition(type_name: str) -> str:
    """The complete message definition of a type: its own text, then each dependency after a
    separator line and "MSG: <type>"."""
    blocks = [MSG_TEXT[type_name]]
    blocks += [f"{ROS2MSG_SEPARATOR}\nMSG: {name}\n{MSG_TEXT[name]}" for name in _all_dependencies(type_name)]
    return "\n".join(blocks) + "\n"


POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
IMU = "sensor_msgs/msg/Imu"
LOG_DATA_GENERIC = "crazyflie_interfaces/msg/LogDataGeneric"
LOG_DATA_GENERIC_DEFINITION = ros2msg_definition(LOG_DATA_GENERIC)

# -- JSON schemas ------------------------------------------------------------------------------------------

POSE_IN_FRAME = "foxglove.PoseInFrame"
FRAME_TRANSFORM = "foxglove.FrameTransform"
ACCELERATION = "learnest.Acceleration"
VECTOR3_SCHEMA_SUFFIXES = ("Vector3", "Vector3Stamped")
UNIT_NAMES = {"g": "g", "m/s^2": "m/s^2", "m/s2": "m/s^2", "m/s²": "m/s^2", "m s^-2": "m/s^2"}

_TIME_SCHEMA = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                 "nsec": {"type": "integer", "minimum": 0}}}
_XYZ = {"type": "object", "properties": {axis: {"type": "number"} for axis in "xyz"}}
_XYZW = {"type": "object", "properties": {axis: {"type": "number"} for axis in "xyzw"}}
POSE_IN_FRAME_JSON_SCHEMA = {
    "title": POSE_IN_FRAME, "description": "A timestamped pose in a named coordinate frame",
    "type": "object",
    "properties": {"timestamp": _TIME_SCHEMA, "frame_id": {"type": "string"},
                   "pose": {"type": "object", "properties": {"position": _XYZ, "orientation": _XYZW}}},
}
FRAME_TRANSFORM_JSON_SCHEMA = {
    "title": FRAME_TRANSFORM, "description": "The pose of the child frame in the parent frame",
    "type": "object",
    "properties": {"timestamp": _TIME_SCHEMA, "parent_frame_id": {"type": "string"},
                   "child_frame_id": {"type": "string"}, "translation": _XYZ, "rotation": _XYZW},
}
ACCELERATION_JSON_SCHEMA = {
    "title": ACCELERATION,
    "description": "Accelerometer reading: specific force in the body frame (+1 g along body z at rest)",
    "type": "object",
    "properties": {"timestamp": _TIME_SCHEMA, "frame_id": {"type": "string", "default": "body"},
                   **{axis: {"type": "number"} for axis in "xyz"},
                   "unit": {"type": "string", "enum": ["g", "m/s^2"]}},
    "required": ["x", "y", "z"],
}
VECTOR3_JSON_SCHEMA = {"title": "Vector3Stamped", "type": "object",
                       "properties": {"timestamp": _TIME_SCHEMA, **{axis: {"type": "number"} for axis in "xyz"}}}


# -- which schemas may be read ---------------------------------------------------------------------------

def ros_type(schema_name: str) -> str:
    """"pkg/Type" and "pkg/msg/Type" name the same ROS 2 type."""
    parts = schema_name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else schema_name


def is_vector3_schema(schema_name: str) -> bool:
    """Whether the schema name's last part (after "/" or ".") is Vector3 or Vector3Stamped."""
    return schema_name.replace("/", ".").split(".")[-1] in VECTOR3_SCHEMA_SUFFIXES


def is_candidate_schema(message_encoding: str, schema_name: str) -> bool:
    """Whether messages of this encoding and schema may be a pose or an acceleration (their payloads
    are kept while the file is scanned)."""
    if message_encoding == "cdr":
        return ros_type(schema_name) in (POSE_STAMPED, TRANSFORM_STAMPED, IMU, LOG_DATA_GENERIC)
    if message_encoding == "json":
        return schema_name in (POSE_IN_FRAME, FRAME_TRANSFORM, ACCELERATION) or is_vector3_schema(schema_name)
    return False
