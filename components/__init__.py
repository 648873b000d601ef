"""Built-in component plugins: simulated sensor drivers, demo talker/listener and the rosbag2 recorder."""
