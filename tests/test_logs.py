"""Core modules' Python logging reaches the node's ROS logger (console, /rosout, the bag)."""
import logging

import pytest

from drift_control.nodes.logs import RosLogHandler


class FakeRosLogger:
    def __init__(self):
        self.lines = []

    def __getattr__(self, severity):
        return lambda text: self.lines.append((severity, text))


@pytest.fixture(autouse=True)
def logging_enabled():
    """Another test's closed loop may have called logging.disable (sweep.run_seed does)."""
    saved = logging.root.manager.disable
    logging.disable(logging.NOTSET)
    yield
    logging.disable(saved)


def test_records_go_to_the_ros_logger_at_their_severity():
    ros = FakeRosLogger()
    log = logging.getLogger('drift_control.reference_test')
    handler = RosLogHandler(ros)
    log.addHandler(handler)
    log.setLevel(logging.DEBUG)
    try:
        log.warning('lookup clamped at s=%.1f m', 3.0)
        log.info('selected')
        log.error('boom')
        log.debug('detail')
    finally:
        log.removeHandler(handler)
    assert ros.lines == [('warning', 'drift_control.reference_test: lookup clamped at s=3.0 m'),
                         ('info', 'drift_control.reference_test: selected'),
                         ('error', 'drift_control.reference_test: boom'),
                         ('debug', 'drift_control.reference_test: detail')]


def test_a_failing_ros_logger_never_raises_into_the_caller():
    class Broken:
        def warning(self, text):
            raise RuntimeError('context gone')
    log = logging.getLogger('drift_control.broken_test')
    handler = RosLogHandler(Broken())
    log.addHandler(handler)
    logging.raiseExceptions, saved = False, logging.raiseExceptions
    try:
        log.warning('still fine')
    finally:
        log.removeHandler(handler)
        logging.raiseExceptions = saved


def test_one_handler_logs_every_severity_through_a_real_rclpy_logger():
    """rclpy refuses a second severity from one call site: each must get through all the same."""
    rclpy_logging = pytest.importorskip('rclpy.logging')
    failed = []

    class Recording(RosLogHandler):
        def handleError(self, record):
            failed.append(record.getMessage())
    log = logging.getLogger('drift_control.severity_test')
    handler = Recording(rclpy_logging.get_logger('severity_test'))
    log.addHandler(handler)
    try:
        log.warning('ACTIVE_FULL -> OFF')
        log.info('armed')
        log.error('lost')
        log.warning('ACTIVE_FULL -> OFF again')
    finally:
        log.removeHandler(handler)
    assert failed == []
