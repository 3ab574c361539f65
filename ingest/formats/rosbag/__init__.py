"""ROS bags -> canonical Flight: ROS 2 sqlite3 storage files (.db3, the Humble default) and ROS 1 bags (.bag),
read with `rosbags` (pure Python); plus a writer of such bags for the simulator and the tests.

Modules: `container` (a bag opened with rosbags: its connections as channels, the candidate messages kept,
ROS 1 chunk decompression capped), `reader` (`sniff`, `read`), `writer` (bags of a flight).

The messages go through the same path as an MCAP recording's (formats.mcap: `channels` classifies,
`selection` chooses the pose and acceleration topics, `reader.read_channels` decodes, cleans and builds the
Flight), so the message types, the topic choice, the candidate list in errors and the meta are the same:
meta["adapter"] is "rosbag-ros2" or "rosbag-ros1", the details are in meta["rosbag"].

A ROS 2 bag is a folder (metadata.yaml + storage files); an upload is one file.  A lone .db3 is read with
rosbags' support for raw storage files (its `topics` and `messages` tables; the type definitions come from
the file when it has them (Iron and later), otherwise from the standard ROS 2 Humble type store plus the
Crazyflie types learnest knows: crazyflie_interfaces/LogDataGeneric and
motion_capture_tracking_interfaces/NamedPose(Array)).  metadata.yaml is not needed and not read, so a bag
whose metadata.yaml declares per-message compression cannot be read from its .db3 alone (the messages do not
decode; say so).  A bag split over several .db3 files is several uploads.  A ROS 2 bag stored as MCAP is an
.mcap file and is read by formats.mcap.
"""
