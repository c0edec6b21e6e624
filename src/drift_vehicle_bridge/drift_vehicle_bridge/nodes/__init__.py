"""rclpy nodes of drift_vehicle_bridge: thin wrappers that turn messages into calls of the core."""
