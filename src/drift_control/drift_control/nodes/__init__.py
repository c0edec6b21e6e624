"""rclpy nodes of drift_control: thin wrappers that turn messages into calls of the core."""
