"""MCAP recordings (ROS 2 bags and JSON-encoded channels) -> canonical Flight; plus writers for the
simulator and the tests.

Modules: `schemas` (the message types read and written), `container` (the file scanned front to back:
schemas, channels, messages, damage), `channels` (which channel is pose, which is acceleration),
`extractors` (one decoded message -> time stamp, values, unit), `inputs` (the Crazyflie's inputs from
LogDataGeneric topics, crazyflies.yaml), `reader` (`read`: topic choice, decoding,
cleaning, the Flight), `writer` (ROS 2 bags and JSON MCAPs of a flight).

What is read
  ROS 2 channels (message encoding "cdr", schema encoding "ros2msg", decoded with mcap_ros2):
    pose          geometry_msgs/msg/PoseStamped, geometry_msgs/msg/TransformStamped (vicon_bridge style);
                  position in m, orientation quaternion (x, y, z, w)
    acceleration  sensor_msgs/msg/Imu: linear_acceleration, m/s², body (IMU) frame, specific force (REP 145)
                  crazyflie_interfaces/msg/LogDataGeneric: `values` in the order of the log block's
                  variables, which the message does not carry.  `log_variables` maps a topic to its
                  variable names; without an entry, a topic whose last name part contains "acc" is read
                  as [acc.x, acc.y, acc.z] in g (what the Crazyflie logs).  `timestamp` (ms since boot)
                  is another clock and is not used.
    inputs        crazyflie_interfaces/msg/LogDataGeneric topics whose variables (from `log_variables`) include
                  Crazyflie variables of ingest.formats.crazyflie_variables (motor.m1..m4, pwm.m1_pwm..,
                  pm.vbat, pm.vbatMV, rpm.m1..m4, controller.cmd_thrust, ctrlLee.thrustSI, gyro.x/y/z, ...)
                  become the Flight channels a uSD or cfclient log gives (motors, vbat, rotor_speed,
                  thrust_cmd, thrust_si, gyro, ...), converted by the same unit converters, on the pose's
                  clock (`inputs`; which topic gave which channel: meta["mcap"]["inputs"]).
  log_variables: given to `read`, or else taken from crazyswarm2's configuration beside the recording,
  `<stem>_crazyflies.yaml` or `crazyflies.yaml` (its firmware_logging.custom_topics under all, robot_types
  and robots: topic NAME of robot ROBOT is /ROBOT/NAME).
  JSON channels (message encoding "json"):
    pose          foxglove.PoseInFrame  {timestamp: {sec, nsec}, frame_id, pose: {position: {x, y, z},
                                         orientation: {x, y, z, w}}}
                  foxglove.FrameTransform {timestamp, parent_frame_id, child_frame_id,
                                           translation: {x, y, z}, rotation: {x, y, z, w}}
    acceleration  learnest.Acceleration (ACCELERATION_JSON_SCHEMA)
                                        {timestamp: {sec, nsec}, frame_id: "body", x, y, z, unit}
                  body-frame specific force (+1 g along body z at rest); unit "g" or "m/s^2".
                  Also a Vector3-like schema (name ending in "Vector3" or "Vector3Stamped") on a topic
                  whose name contains "acc": {timestamp, x, y, z} with an optional unit.
                  Without a unit the topic's unit is inferred from its median magnitude (≈ 1 -> g,
                  ≈ 9.8 -> m/s²) and the inference is noted in meta["mcap"]["warnings"].

Topic choice: automatic when exactly one pose topic and one acceleration topic carry messages;
otherwise `reader.read(path, pose_topic=..., accel_topic=...)`.  Ambiguity and absence are IngestErrors that
list the candidates / all topics with their schemas.

Time: a topic's header stamps (JSON: "timestamp") when every message has a nonzero one, otherwise the
MCAP log_time of every message of that topic.  If the pose and acceleration topics end up on different
sources, both use log_time (one clock; noted in the warnings).  Times are taken relative to the earliest
selected message (meta["mcap"]["time_origin_ns"]) so that float seconds keep nanosecond resolution.

Damage: the file is read front to back with mcap's non-seeking StreamReader, so a file cut off mid-write
(no summary, half a chunk) still yields every complete chunk before the cut.  A chunk that does not
decompress or fails its CRC check is skipped and reading goes on.  Both are noted in meta["mcap"]["warnings"].  What
cannot become a Flight (not MCAP, empty, nothing usable) is an IngestError naming the file.  Messages are
sorted by time; repeated time stamps, non-finite values and non-unit quaternions are dropped and counted
in meta["mcap"]["streams"].
"""
