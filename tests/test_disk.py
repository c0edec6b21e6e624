"""Disk watch: a warning before the disk runs out, a stop while the bag can still be closed."""
from types import SimpleNamespace

import pytest

from drift_tools.disk import MIB, DiskLevel, DiskLimits, DiskWatch


class FakeDisk:
    def __init__(self, free):
        self.free = free

    def __call__(self, path):
        return SimpleNamespace(free=self.free)


def test_plenty_of_space_is_ok_and_says_how_long_it_lasts():
    disk = FakeDisk(100_000 * MIB)
    watch = DiskWatch('.', DiskLimits(), usage=disk)
    assert watch.check(0, 0.0).level == DiskLevel.OK
    for k in range(1, 40):                        # 1 MiB/s for 39 s
        status = watch.check(k * MIB, float(k))
    assert status.level == DiskLevel.OK and status.rate == pytest.approx(MIB, rel=0.05)
    assert 'MiB/s' in status.message and ' h at ' in status.message


def test_warns_on_time_left_before_the_floor():
    disk = FakeDisk(5000 * MIB)                   # above the 2 GiB floor...
    watch = DiskWatch('.', DiskLimits(warn_time_left=600.0, rate_tau=1.0), usage=disk)
    watch.check(0, 0.0)
    status = watch.check(10 * 10 * MIB, 10.0)     # ...but 10 MiB/s empties it in ~8 min
    assert status.level == DiskLevel.WARN and 'disk space low' in status.message


def test_warns_below_the_floor_and_stops_before_full():
    disk = FakeDisk(1000 * MIB)
    watch = DiskWatch('.', DiskLimits(), usage=disk)
    assert watch.check(0, 0.0).level == DiskLevel.WARN
    disk.free = 10 * MIB
    status = watch.check(0, 1.0)
    assert status.level == DiskLevel.STOP and 'recording stopped' in status.message


def test_limits_are_checked():
    with pytest.raises(ValueError, match='stop_free <= warn_free'):
        DiskLimits(warn_free=MIB, stop_free=2 * MIB)
    with pytest.raises(ValueError, match='rate_tau'):
        DiskLimits(rate_tau=0.0)
