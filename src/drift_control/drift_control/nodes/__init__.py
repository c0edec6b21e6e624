"""rclpy nodes of drift_control: thin wrappers that turn messages into calls of the core."""
from drift_control.nodes.stops import install_if_node_process

install_if_node_process()   # before the heavy imports of the node modules
