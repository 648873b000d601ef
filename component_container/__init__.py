"""rclpy component container: loads nodes by plugin name and connects them intra-process."""
