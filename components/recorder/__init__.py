"""The rosbag2-compatible recorder component: node, intake, writer thread; the files are baglib's."""
