"""The rosbag2-compatible recorder: its storage layer writes standard bags from serialized messages."""
