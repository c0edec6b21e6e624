"""The lock that lets ``ros``/``realtime`` tests run alone under pytest-xdist (run_alone.py)."""
import fcntl
import threading
from types import SimpleNamespace

import pytest

from run_alone import RoomLock, keep_after, run_alone_first, runs_alone, scheduling


def _enter_in_thread(lock, alone, order, name):
    def run():
        lock.enter(alone)
        order.append(name)
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


@pytest.fixture
def locks(tmp_path):
    made = [RoomLock(tmp_path / 'room') for _ in range(3)]   # one per "worker"
    yield made
    for lock in made:
        lock.close()


def test_an_alone_test_waits_for_the_running_ones_and_then_has_the_room(locks):
    a, b, c = locks
    a.enter(alone=False)
    b.enter(alone=False)
    order = []
    writer = _enter_in_thread(c, True, order, 'alone')
    writer.join(0.3)
    assert order == [], 'entered while two tests ran'
    a.leave()
    writer.join(0.3)
    assert order == [], 'entered while one test ran'
    b.leave()
    writer.join(5.0)
    assert order == ['alone']
    reader = _enter_in_thread(a, False, order, 'beside')
    reader.join(0.3)
    assert order == ['alone'], 'an ordinary test started beside the one running alone'
    c.leave()
    reader.join(5.0)
    assert order == ['alone', 'beside']


def test_a_waiting_alone_test_is_not_overtaken_by_new_ordinary_ones(locks):
    a, b, c = locks
    a.enter(alone=False)
    order = []
    writer = _enter_in_thread(c, True, order, 'alone')
    writer.join(0.3)                    # now waiting for a, holding the gate
    reader = _enter_in_thread(b, False, order, 'next')
    reader.join(0.3)
    assert order == [], 'a new ordinary test started while one waited to run alone'
    a.leave()
    writer.join(5.0)
    assert order == ['alone']
    c.leave()
    reader.join(5.0)
    assert order == ['alone', 'next']


def test_the_same_mode_again_is_a_no_op_and_a_change_lets_go_first(locks):
    a, b, _ = locks
    a.enter(alone=True)
    a.enter(alone=True)
    assert a.held == fcntl.LOCK_EX
    a.enter(alone=False)                 # from alone to shared: others may join now
    assert a.held == fcntl.LOCK_SH
    order = []
    _enter_in_thread(b, False, order, 'beside').join(5.0)
    assert order == ['beside'], 'still exclusive after changing to shared'


class _item(SimpleNamespace):
    def __init__(self, nodeid, *markers):
        super().__init__(nodeid=nodeid, markers=markers)

    def get_closest_marker(self, name):
        return name if name in self.markers else None


def test_only_consecutive_alone_tests_keep_the_room():
    assert runs_alone(_item('a', 'ros')) and runs_alone(_item('a', 'realtime'))
    assert not runs_alone(_item('a', 'slow'))
    assert not runs_alone(_item('a', 'ros', 'no_rates')), 'no rate to keep: it shares'
    assert keep_after(_item('a', 'ros'), _item('b', 'realtime'))
    assert not keep_after(_item('a', 'ros'), _item('a')), 'an ordinary test next'
    assert not keep_after(_item('a'), _item('a'))
    assert not keep_after(_item('a', 'ros'), None)


def test_the_alone_tests_go_first_and_the_scheduler_makes_them_one_unit(tmp_path):
    items = [_item('tests/test_a.py::t1'), _item('tests/test_b.py::t1', 'ros'),
             _item('tests/test_a.py::t2'), _item('tests/test_c.py::t1', 'realtime')]
    ids = tmp_path / 'room.alone'
    run_alone_first(items, ids)
    assert [i.nodeid for i in items] == ['tests/test_b.py::t1', 'tests/test_c.py::t1',
                                         'tests/test_a.py::t1', 'tests/test_a.py::t2']
    config = SimpleNamespace(getvalue=lambda name: ['2*popen'] if name == 'tx' else None)
    sched = scheduling(config, None, ids)
    assert [sched._split_scope(i.nodeid) for i in items] == [
        'run-alone', 'run-alone', 'tests/test_a.py', 'tests/test_a.py']
