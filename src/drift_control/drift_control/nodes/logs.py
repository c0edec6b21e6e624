"""Python ``logging`` of the core modules into the node's ROS logger: console, ``/rosout``, bag.

The algorithm modules log through ``logging`` (they import no ROS). In a node those lines would
reach stderr only; routed here they get the node's name, a severity and a time, and are
published on ``/rosout``, which the recorder keeps.
"""
from __future__ import annotations

import logging

class RosLogHandler(logging.Handler):
    """Forwards each record to an rclpy logger at the matching severity.

    rclpy keys a logger's severity by the line that calls it and refuses another severity from
    the same line: each severity has its own call here.
    """

    def __init__(self, ros_logger):
        super().__init__()
        self.ros = ros_logger

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text, level, ros = f'{record.name}: {record.getMessage()}', record.levelno, self.ros
            if level >= logging.CRITICAL:
                ros.fatal(text)
            elif level >= logging.ERROR:
                ros.error(text)
            elif level >= logging.WARNING:
                ros.warning(text)
            elif level >= logging.INFO:
                ros.info(text)
            else:
                ros.debug(text)
        except Exception:   # noqa: BLE001 - a log line must never break the node
            self.handleError(record)


def route_python_logging(node, level: int = logging.INFO) -> RosLogHandler:
    """Send the root logger's records (``level`` and up) to ``node``'s logger; returns the
    handler (remove it from the root logger to undo)."""
    handler = RosLogHandler(node.get_logger())
    root = logging.getLogger()
    root.addHandler(handler)
    root.setLevel(min(root.level or level, level) if root.level else level)
    return handler
