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
    "geometry_msgs/msg/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/msg/PoseWithCovarianceStamped": "std_msgs/Header header\nPoseWithCovariance pose",
    "geometry_msgs/msg/Twist": "Vector3 linear\nVector3 angular",
    "geometry_msgs/msg/TwistWithCovariance": "Twist twist\nfloat64[36] covariance",
    "nav_msgs/msg/Odometry": ("std_msgs/Header header\nstring child_frame_id\n"
                              "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist"),
    "tf2_msgs/msg/TFMessage": "geometry_msgs/TransformStamped[] transforms",
    # motion_capture_tracking_interfaces (what crazyswarm2's mocap node publishes on /poses)
    "motion_capture_tracking_interfaces/msg/NamedPose": "string name\ngeometry_msgs/Pose pose",
    "motion_capture_tracking_interfaces/msg/NamedPoseArray": ("std_msgs/Header header\n"
                                                              "NamedPose[] poses"),
}
MSG_DEPENDENCIES = {
    "std_msgs/msg/Header": ["builtin_interfaces/msg/Time"],
    "geometry_msgs/msg/Pose": ["geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion"],
    "geometry_msgs/msg/Transform": ["geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion"],
    "geometry_msgs/msg/PoseStamped": ["std_msgs/msg/Header", "geometry_msgs/msg/Pose"],
    "geometry_msgs/msg/TransformStamped": ["std_msgs/msg/Header", "geometry_msgs/msg/Transform"],
    "sensor_msgs/msg/Imu": ["std_msgs/msg/Header", "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Vector3"],
    "crazyflie_interfaces/msg/LogDataGeneric": ["std_msgs/msg/Header"],
    "geometry_msgs/msg/PoseWithCovariance": ["geometry_msgs/msg/Pose"],
    "geometry_msgs/msg/PoseWithCovarianceStamped": ["std_msgs/msg/Header", "geometry_msgs/msg/PoseWithCovariance"],
    "geometry_msgs/msg/Twist": ["geometry_msgs/msg/Vector3"],
    "geometry_msgs/msg/TwistWithCovariance": ["geometry_msgs/msg/Twist"],
    "nav_msgs/msg/Odometry": ["std_msgs/msg/Header", "geometry_msgs/msg/PoseWithCovariance",
                              "geometry_msgs/msg/TwistWithCovariance"],
    "tf2_msgs/msg/TFMessage": ["geometry_msgs/msg/TransformStamped"],
    "motion_capture_tracking_interfaces/msg/NamedPose": ["geometry_msgs/msg/Pose"],
    "motion_capture_tracking_interfaces/msg/NamedPoseArray": ["std_msgs/msg/Header",
                                                              "motion_capture_tracking_interfaces/msg/NamedPose"],
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
POSE_WITH_COVARIANCE_STAMPED = "geometry_msgs/msg/PoseWithCovarianceStamped"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
NAMED_POSE_ARRAY = "motion_capture_tracking_interfaces/msg/NamedPoseArray"
NAMED_POSE = "motion_capture_tracking_interfaces/msg/NamedPose"
# ROS types that carry one pose per message, and those that carry the poses of several bodies (named)
SINGLE_POSE_TYPES = (POSE_STAMPED, TRANSFORM_STAMPED, POSE_WITH_COVARIANCE_STAMPED, ODOMETRY)
MULTI_POSE_TYPES = (TF_MESSAGE, NAMED_POSE_ARRAY)
# Types outside the standard ROS 2 type store that the reader knows the definitions of (a bag without
# stored definitions, e.g. a Humble .db3, still decodes them)
EXTRA_TYPES = (LOG_DATA_GENERIC, NAMED_POSE, NAMED_POSE_ARRAY)

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

# ROS message encodings: CDR (ROS 2, MCAP and .db3) and ROS 1 serialization (.bag; decoded by rosbags)
ROS_ENCODINGS = ("cdr", "ros1")


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
    if message_encoding in ROS_ENCODINGS:
        return ros_type(schema_name) in (*SINGLE_POSE_TYPES, *MULTI_POSE_TYPES, IMU, LOG_DATA_GENERIC)
    if message_encoding == "json":
        return schema_name in (POSE_IN_FRAME, FRAME_TRANSFORM, ACCELERATION) or is_vector3_schema(schema_name)
    return False
