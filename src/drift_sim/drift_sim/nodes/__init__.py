"""rclpy nodes of drift_sim: thin wrappers that turn messages into calls of the core."""
