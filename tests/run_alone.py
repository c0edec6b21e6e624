"""Tests that keep wall-clock deadlines run alone while the rest of the suite runs in parallel.

With pytest-xdist every worker takes this lock around each test: shared for an ordinary test,
exclusive for one marked ``ros`` (real nodes in real processes, real-time rates) or ``realtime``,
unless it is also marked ``no_rates`` (it starts ROS processes but keeps no rate or deadline: the
colcon build, 47 s of it).
A worker that wants it exclusive first closes a gate, so the others cannot keep it shared for
ever; it then waits until the tests running elsewhere have ended, and no other test starts until
it lets go. ``make test`` (``--dist loadfile``) hands all of them to one worker first, as one unit
(``RunAloneScheduling``), which keeps the lock from one to the next: the others wait once, not
before each. Every other unit is a test file, as xdist's ``loadfile`` makes them.
"""
import fcntl
import os

ALONE_MARKERS = ('ros', 'realtime')


def runs_alone(item) -> bool:
    return (any(item.get_closest_marker(name) for name in ALONE_MARKERS)
            and not item.get_closest_marker('no_rates'))


class RoomLock:
    """A readers-writer lock between processes on two files (``flock``), writers first."""

    def __init__(self, path):
        self.ids_file = f'{path}.alone'   # the ids of the tests that run alone (the scheduler's)
        self._gate = open(f'{path}.gate', 'a+')
        self._room = open(path, 'a+')
        self.held = None        # fcntl.LOCK_SH, fcntl.LOCK_EX or None

    def enter(self, alone: bool) -> None:
        mode = fcntl.LOCK_EX if alone else fcntl.LOCK_SH
        if self.held == mode:
            return
        self.leave()
        fcntl.flock(self._gate, fcntl.LOCK_EX)
        try:
            fcntl.flock(self._room, mode)
        finally:
            fcntl.flock(self._gate, fcntl.LOCK_UN)
        self.held = mode

    def leave(self) -> None:
        if self.held is not None:
            fcntl.flock(self._room, fcntl.LOCK_UN)
            self.held = None

    def close(self) -> None:
        self.leave()
        self._gate.close()
        self._room.close()


def keep_after(item, nextitem) -> bool:
    """Hold an exclusive lock on into the next test when it runs alone too."""
    return nextitem is not None and runs_alone(item) and runs_alone(nextitem)


def run_alone_first(items, ids_file) -> None:
    """In a worker's collection: the tests that run alone first; their ids to ``ids_file``."""
    items.sort(key=lambda item: not runs_alone(item))      # stable: collection order within
    text = ''.join(f'{item.nodeid}\n' for item in items if runs_alone(item))
    tmp = f'{ids_file}.{os.getpid()}'
    with open(tmp, 'w') as out:
        out.write(text)
    os.replace(tmp, ids_file)              # every worker writes the same: the last one stands


def scheduling(config, log, ids_file):
    """``loadfile`` with the tests that run alone as one unit of their own (xdist controller)."""
    from xdist.scheduler import LoadFileScheduling

    class RunAloneScheduling(LoadFileScheduling):
        _alone = None

        def _split_scope(self, nodeid: str) -> str:
            if self._alone is None:       # first asked once every worker has collected
                with open(ids_file) as ids:
                    self._alone = frozenset(ids.read().splitlines())
            return 'run-alone' if nodeid in self._alone else super()._split_scope(nodeid)

    return RunAloneScheduling(config, log)
