"""rclpy nodes of drift_tools: thin wrappers that turn messages into calls of the core."""
