"""The bridge's view of the recorder: its reports passed on, its silence an error."""
import pytest

from drift_vehicle_bridge.peers import ERROR, OK, WARN, HeartbeatWatch


def test_a_peer_never_heard_of_is_not_reported():
    assert HeartbeatWatch('recorder').status(100.0) is None


def test_reports_pass_on_and_silence_is_an_error():
    watch = HeartbeatWatch('recorder', timeout=3.0)
    watch.report(OK, 'recording; 900 GiB free', 10.0)
    assert watch.status(12.0) == (OK, 'recorder: recording; 900 GiB free')
    watch.report(WARN, 'recording; disk space low', 13.0)
    assert watch.status(13.5)[0] == WARN
    level, message = watch.status(16.5)
    assert level == ERROR and 'silent for 3.5 s' in message


def test_levels_from_ros_messages_are_ints():
    msgs = pytest.importorskip('diagnostic_msgs.msg')
    from drift_vehicle_bridge.nodes.convert import level_of, peer_status
    status = msgs.DiagnosticStatus(name='recorder', level=msgs.DiagnosticStatus.ERROR)
    assert level_of(status) == ERROR
    assert level_of(peer_status('x', WARN, 'm')) == WARN
