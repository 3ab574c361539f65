"""MCAP recordings (ROS 2 bags and JSON-encoded channels)."""
