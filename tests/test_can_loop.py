"""The whole loop over the car's link: sim -> link -> bridge -> reference -> NMPC -> bridge -> sim.

Two links: classic CAN (``sim_can``: python-can udp_multicast, the DBC, E2E P01) and FlexRay
PDUs through an Ethernet gateway (``sim_flexray``: the ARXML's PDUs with AUTOSAR Socket Adaptor
headers over UDP, E2E P02). For each, the slow tests share one run of the graph in real time
through ``scripts/run_in_netns.sh`` (a private network namespace with only loopback, so no
datagram leaves the machine), recorded and read back: one judges the link and the bridge, the
other the drift the controller drives through them.
The fast tests pin down ``auto_arm``: simulated buses only, arms once the state allows it,
and a drop to OFF after having been ACTIVE stays latched.
"""
import math
import os
import subprocess
import threading
import time
from dataclasses import replace
from types import SimpleNamespace

import can
import numpy as np
import pytest

from conftest import PYTHON, REPO
from drift_control.params import ParamError
from drift_control.signals import Command, Mode, VehicleState
from drift_vehicle_bridge.gateway import Gateway
from drift_vehicle_bridge.params import load_bridge_params
from drift_vehicle_bridge.vehicle_side import CarSide
from test_bridge_udp import NETNS_REASON

# graph, description, domain id, further run_stack arguments. The sensor mode over CAN FD
# (('sim_canfd', 'can/drift_vehicle_fd.dbc', 112, ('--sensors', 'realistic'))) passes these
# tests, but failed 2 of 14 runs on a loaded machine (docs/vehicle_bridge.md, sensor mode); after
# the start gate of the recorded runs 20 of 20 idle and 63 of 64 under a campaign's load (the one
# failure's output was not kept): not in the suite until that one is understood.
LINKS = {'can': ('sim_can', 'can/drift_vehicle.dbc', 110, ()),
         'flexray': ('sim_flexray', 'flexray/drift_vehicle.arxml', 111, ())}
RUN_S = 12.0                    # scenario time, from the bridge's first request on [s]
WALL_MAX_S = 40.0               # the whole launch, start-up included, at most [s]
SCENARIO = 'drift_hold_dry'     # handed over in an established 30 deg drift (see its yaml)
DRIFT_DEG, SPIN_DEG = 20.0, 75.0
STALL_S = load_bridge_params().monitor.frame_timeout   # a longer simulator stall drops the bridge
TAKEN_MS = 40.0   # CPU time the machine took within 100 ms (both CPUs) that stalls the loop
DROP_LEAD_S = 0.2  # before a drop: the heartbeat's 60 ms and the stall that led to it [s]


# ---------------------------------------------------------------- auto_arm (fast, no ROS)

@pytest.mark.parametrize('interface', ['socketcan', 'pcan', 'kvaser', 'vector', 'slcan'])
def test_auto_arm_is_refused_on_a_car_bus(interface):
    with pytest.raises(ParamError, match='auto_arm'):
        load_bridge_params(None, {'bus': {'interface': interface, 'channel': 'can0'},
                                  'auto_arm': True})


def test_auto_arm_is_off_by_default_and_allowed_on_simulated_buses():
    assert load_bridge_params().auto_arm is False
    for interface in ('virtual', 'udp_multicast'):
        assert load_bridge_params(None, {'bus': {'interface': interface},
                                         'auto_arm': True}).auto_arm


def _calm(now, **kw):
    state = VehicleState(stamp=now, V=8.0, beta=-0.05, r=0.4, vx=8.0, vy=-0.4,
                         wheel_speeds=(24.0, 24.0, 24.5, 24.5), delta=0.03, drive_torque=400.0)
    return replace(state, **kw)


def test_auto_arm_waits_for_hands_off_then_latches_off_after_a_takeover():
    params = load_bridge_params(None, {'auto_arm': True})
    with can.Bus('auto_arm_t', interface='virtual') as car_bus, \
            can.Bus('auto_arm_t', interface='virtual') as our_bus:
        car = CarSide(car_bus)
        gw = Gateway(our_bus, car.codec, params)
        modes = []
        for k in range(120):
            now = 0.01 * k
            hands_on = k < 30                          # driver still holds the wheel
            braking = 70 <= k < 75                     # a short brake: takeover
            car.send_state(_calm(now, steering_torque=8.0 if hands_on else 0.5,
                                 brake_pedal=braking))
            if k >= 40:
                gw.set_command(Command(now, -0.1, 0.0, 800.0, Mode.FULL), now)
            gw.step(now)
            car.poll_command(now)
            modes.append(gw.mode.name)
    assert set(modes[:30]) == {'OFF'}, 'no arming while the driver holds the wheel'
    assert modes[30] == 'ARMED', 'armed in the first hands-off cycle, without a request'
    assert modes[45] == 'ACTIVE_FULL' and gw.been_active
    assert modes[69] == 'ACTIVE_FULL' and modes[70] == 'OFF', 'takeover in the same cycle'
    assert gw.modes.reason.name == 'BRAKE_PEDAL'
    assert set(modes[70:]) == {'OFF'}, 'after ACTIVE, OFF is latched: no auto re-arm'


def test_auto_arm_retries_after_an_arm_timeout_before_the_first_command():
    params = load_bridge_params(None, {'auto_arm': True})
    with can.Bus('auto_arm_t2', interface='virtual') as car_bus, \
            can.Bus('auto_arm_t2', interface='virtual') as our_bus:
        car = CarSide(car_bus)
        gw = Gateway(our_bus, car.codec, params)
        n = int((params.mode.arm_timeout + 0.5) / 0.01)
        dropped = False
        for k in range(n):
            now = 0.01 * k
            car.send_state(_calm(now))
            gw.step(now)
            dropped |= gw.modes.reason.name == 'ARM_TIMEOUT'
    assert dropped, 'the controller never answered: ARMED timed out'
    assert gw.mode.name == 'ARMED', 'and was re-armed (the controller may still be starting)'


# ---------------------------------------------------------------- the loop (slow, ROS, netns)

def test_machine_meter_counts_slow_cpus_and_steal_not_noise():
    meter = MachineMeter()
    t = 1000.0 + meter.PERIOD * np.arange(200)
    usual = 50e-6 * (1.0 + 0.4 * (np.arange(200) % 2))     # 50-70 us: noise, never counted
    slow = usual.copy()
    slow[100:120] = 250e-6                                  # 100 ms at 5x the median
    slow[50] = usual[150] = 700e-6                          # one sample each: not a slow CPU
    meter.work = {0: list(zip(t, slow)), 1: list(zip(t, usual))}
    assert meter.worst(t[0], t[90]) == 0.0
    # 20 samples of 5 ms, each 1 - 70 / 250 slow (the median: 70 us, the slow ones included)
    assert meter.worst(t[95], t[125]) == pytest.approx(20 * (1 - 70 / 250) * 5.0)
    tick_ms = 1e3 / os.sysconf('SC_CLK_TCK')
    meter.steal = [(t[0], 0), (t[50], 3), (t[150], 3)]     # 3 ticks stolen at t[50]
    assert meter.worst(t[40], t[60]) == pytest.approx(3 * tick_ms)
    assert meter.worst(t[95], t[125]) == pytest.approx(20 * (1 - 70 / 250) * 5.0), 'apart'


def _longest_run(t, mask) -> float:
    """Longest time [s] ``mask`` stays true in a row."""
    best, start = 0.0, None
    for ti, m in zip(t, mask):
        if m and start is None:
            start = ti
        elif not m and start is not None:
            best, start = max(best, ti - start), None
    return max(best, t[-1] - start) if start is not None else best


def _bridge_diagnostics(messages, name='vehicle_bridge: CAN'):   # not its 'recording' status
    out = []
    for m in messages.get('/diagnostics', []):
        for status in m.msg.status:
            if status.name == name:
                out.append({kv.key: kv.value for kv in status.values})
                out[-1]['_t'] = m.msg.header.stamp.sec + 1e-9 * m.msg.header.stamp.nanosec
    return out


class MachineMeter:
    """CPU time the machine takes from this virtual machine while a run goes, sampled every 5 ms.

    Two ways, both seen on these shared machines: the hypervisor's ``steal`` (/proc/stat), and
    CPUs that keep running but slow, which /proc/stat does not count: with nothing else running,
    a fixed piece of work takes 3-13 times its usual CPU time in 2-5 % of 50 ms windows, on both
    CPUs at once, and every node slows with it. Each CPU has a sampler thread (pinned, real-time
    above the launch where allowed) that times the same work in thread CPU time, so a thread
    that waits for its CPU does not count, only a CPU that runs slow. A sample at least ``SLOW``
    times the run's median, with one of its neighbours, took ``1 - median / sample`` of the time
    since the sample before. 40-220 ms of the two CPUs' time within 100 ms stalls every node at
    once, whatever its priority, and the bridge's 30 ms frame timeout or 60 ms heartbeat trips,
    as it must.
    """

    PERIOD = 0.005
    SLOW = 2.0          # a sample this many times the median: a slow CPU, not noise
    PRIORITY = 50       # above the launch's nodes (10-20), below the kernel's own threads
    WORK = 1000         # iterations of the timed work (~80 us on an idle CPU here)

    def __init__(self):
        self.steal: list[tuple[float, int]] = []   # (time.time(), steal summed over CPUs)
        self.work: dict[int, list[tuple[float, float]]] = {}   # CPU -> (time.time(), CPU s)
        self._stop = threading.Event()
        cpus = sorted(os.sched_getaffinity(0))
        self._threads = [threading.Thread(target=self._run, args=(cpu, cpu == cpus[0]),
                                          daemon=True) for cpu in cpus]
        self._tick_ms = 1e3 / os.sysconf('SC_CLK_TCK')

    def __enter__(self):
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        for thread in self._threads:
            thread.join()

    def _run(self, cpu: int, read_steal: bool):
        try:   # this thread only (Linux): pinned, and above the nodes where allowed
            os.sched_setaffinity(0, {cpu})
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.PRIORITY))
        except OSError:
            pass
        samples = self.work.setdefault(cpu, [])
        while not self._stop.is_set():
            c0 = time.thread_time()
            _fixed_work(self.WORK)
            samples.append((time.time(), time.thread_time() - c0))
            if read_steal:
                try:
                    with open('/proc/stat') as f:
                        total = int(f.readline().split()[8])   # the 'cpu' line: all CPUs
                    self.steal.append((time.time(), total))
                except (OSError, IndexError, ValueError):      # no /proc or no steal column
                    read_steal = False
            self._stop.wait(self.PERIOD)

    def worst(self, start: float, end: float, window: float = 0.1) -> float:
        """Most CPU time [ms] taken within ``window`` [s] anywhere in [start, end]: stolen,
        or lost to CPUs running slow."""
        events = []   # (time, ms taken)
        if len(self.steal) > 1:
            t, v = np.array(self.steal, dtype=float).T
            events += zip(t[1:], np.diff(v) * self._tick_ms)
        for samples in self.work.values():
            if len(samples) < 10:
                continue
            t, w = np.array(samples).T
            # slow in two samples of three: an interrupt or a page fault in one sample is not a
            # slow CPU; each sample stands for the time since the one before (at most 3 periods)
            w = np.median([w, np.roll(w, 1), np.roll(w, -1)], axis=0)
            ratio = w / np.median(w)
            span = np.minimum(np.diff(t, prepend=t[0] - self.PERIOD), 3 * self.PERIOD)
            events += zip(t, np.where(ratio >= self.SLOW, 1.0 - 1.0 / ratio, 0.0) * span * 1e3)
        if not events:
            return 0.0
        t, v = np.array(sorted(events)).T
        total = np.concatenate(([0.0], np.cumsum(v)))
        starts = np.concatenate(([start], t[(t > start) & (t <= end - window)]))
        best = 0.0
        for a in starts:
            best = max(best, total[np.searchsorted(t, a + window)] - total[np.searchsorted(t, a)])
        return float(best)


def _fixed_work(n: int) -> int:
    """The same pure-Python arithmetic every time: what it costs is the CPU's speed."""
    s = 0
    for i in range(n):
        s += i * i
    return s


def _stalls(diags, name: str, who: str, t0: float) -> list[dict]:
    """Each diagnostic period's longest cycle gap past the frame timeout (``CycleWatch``: the
    ``<name>_*_ms`` values) and where its time went; ``machine``: without what the cycle waited
    for a CPU and what the hypervisor took, it would have kept the timeout."""
    out = []
    for d in diags:
        gap = float(d.get(f'{name}_max_ms', 0.0)) / 1e3
        if gap > STALL_S:
            parts = {p: float(d[f'{name}_{p}_ms']) / 1e3 for p in ('ran', 'waited', 'stolen')}
            out.append({'who': who, 't': round(float(d['_t'] - t0), 2), 'gap': round(gap, 3),
                        **{p: round(v, 3) for p, v in parts.items()},
                        'machine': gap - parts['waited'] - parts['stolen'] <= STALL_S})
    return out


def _drop_windows(diags) -> dict[str, tuple[float, float]]:
    """Reason of each drop out of an active mode -> the span that led to it (stamps as
    recorded): the ``DROP_LEAD_S`` before the drop's own stamp, or where a diagnostic lacks it,
    the span between the two diagnostics it fell between."""
    out, before = {}, set()
    for k, d in enumerate(diags):
        now = {key.split('/')[-1] for key in d if key.startswith('drops/ACTIVE_')}
        a, b = (diags[k - 1]['_t'] if k else d['_t'] - 1.0, d['_t'])
        dropped = float(d.get('drop_stamp', math.nan))
        for reason in now - before:
            out[reason] = (dropped - DROP_LEAD_S, dropped) if a <= dropped <= b else (a - 0.1, b)
        before = now
    return out


def _warm_nmpc_codegen():
    """Build the NMPC once here: a fresh checkout compiles its C code (.codegen/) on first use,
    which must not happen inside the real-time run while the simulated car coasts."""
    from drift_control.nmpc import Nmpc
    from drift_control.ocp import load_nmpc_params
    from drift_control.params import load_vehicle
    from drift_control.signals import Mode as ControlMode
    Nmpc(load_vehicle(), load_nmpc_params(), ControlMode.FULL)


def _realtime_prefix() -> list[str]:
    """Round-robin real-time priority for the launch where allowed, else nice -5.

    The loop runs against the bridge's 30 ms frame timeouts: a simulator stalled longer by other
    jobs on the machine drops the bridge to OFF. The nodes sleep between their timers, and the
    kernel's RT throttling still leaves 5 % of each second to everything else.
    """
    if subprocess.run(['chrt', '-r', '10', 'true'], capture_output=True).returncode == 0:
        return ['chrt', '-r', '10']
    return ['nice', '-n', '-5']


@pytest.fixture(scope='module', params=list(LINKS))
def can_loop(request, tmp_path_factory):
    """One run of the link's graph (RUN_S of the scenario once the bridge engaged the car:
    start-up takes 3-5 s, more on a loaded machine), recorded and read back."""
    if NETNS_REASON is not None:
        pytest.skip(NETNS_REASON)
    graph, description, domain_id, extra = LINKS[request.param]
    from drift_tools.bag import read_bag
    from drift_tools.report import run_metrics
    from drift_tools.timeseries import series_from_bag

    _warm_nmpc_codegen()
    for attempt in (1, 2):
        bag = tmp_path_factory.mktemp('can_loop') / 'bag'
        t0 = time.monotonic()
        with MachineMeter() as meter:
            proc = subprocess.run(
                [*_realtime_prefix(), str(REPO / 'scripts' / 'run_in_netns.sh'),
                 '--duration', str(WALL_MAX_S), '--sim-duration', str(RUN_S),
                 '--scenario', SCENARIO, '--bag', str(bag), '--domain-id', str(domain_id),
                 '--graph', graph, '--kill-timeout', '5', '--no-summary', *extra],
                env={**os.environ, 'PYTHON': PYTHON}, capture_output=True, text=True, timeout=60)
        wall = time.monotonic() - t0
        assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]
        messages = read_bag(bag)
        run = series_from_bag(messages)
        t = run.truth['t']
        car = _bridge_diagnostics(messages, 'car side')
        # the bridge's diagnostics after the car's last step see the state PDUs stop, as they
        # must, and are left out
        diags = [d for d in _bridge_diagnostics(messages) if d['_t'] <= run.t0 + t[-1]]
        # the simulated car's and the bridge's cycles late past the frame timeout, start-up
        # included (a publish that slept 333 ms there once dropped the link: docs/dds.md), each
        # with where its time went
        stalls = _stalls(car, 'step_gap', 'car', run.t0) + \
            _stalls(diags, 'cycle_gap', 'bridge', run.t0)
        # CPU time the machine took in what led to each drop out of ACTIVE [ms]
        taken = {r: meter.worst(a, b) for r, (a, b) in _drop_windows(diags).items()}
        # a cycle the machine delayed past the frame timeout (its CPU taken by the hypervisor or
        # other tasks) drops the bridge to OFF, as it must on a car: that run says nothing about
        # the loop, run once more (printed); a cycle late by its own doing is judged
        machine = [s for s in stalls if s['machine']] + \
            [f'{r}: {ms:.0f} ms taken' for r, ms in taken.items() if ms >= TAKEN_MS]
        if not machine or attempt == 2:
            break
        print(f'{graph} run {attempt}: the machine delayed the link: {machine}; running again')
    for d in diags + car:
        d['_t'] -= run.t0
        if 'drop_stamp' in d:
            d['drop_stamp'] = float(d['drop_stamp']) - run.t0
    m = run_metrics(run)
    stall = max((float(d['step_gap_max_ms']) for d in car), default=0.0) / 1e3
    bridge_stall = max((float(d['cycle_gap_max_ms']) for d in diags), default=0.0) / 1e3
    timing = (f'simulator {(len(t) - 1) / (t[-1] - t[0]):.1f} steps/s, the car\'s longest step '
              f'gap {1e3 * stall:.0f} ms, the bridge\'s longest cycle gap {1e3 * bridge_stall:.0f}'
              f' ms (frame timeout 30 ms; past it: {stalls or "none"}), NMPC solve p99 '
              f'{m["solve_time_ms_p99"]:.1f} ms, max {m["solve_time_ms_max"]:.1f} ms')
    print(f'{graph} run: wall {wall:.1f} s; {timing}; bag {bag}')
    from drift_vehicle_bridge.codec import Codec
    from drift_control.params import config_dir
    codec = Codec.load(config_dir() / description)
    # the most the machine took anywhere in the run once the bridge was up [ms in 100 ms]
    taken_max = meter.worst(diags[0]['_t'] + run.t0, diags[-1]['_t'] + run.t0) if diags else 0.0
    return SimpleNamespace(run=run, metrics=m, diags=diags, car=car, wall=wall, timing=timing,
                           link=request.param, sensors=bool(extra), codec=codec, stall=stall,
                           bridge_stall=bridge_stall, stalls=stalls, taken=taken,
                           taken_max=taken_max)


def _pdu_hz(can_loop, name: str) -> float:
    """A state PDU's rate: 100 Hz, in sensor mode its slowest sensor unit's."""
    rate = load_bridge_params().sensors.rate
    units = can_loop.codec.pdu_units[name] if can_loop.sensors else ()
    return min((rate[u] for u in units), default=100.0)


def _stamped_rates(first: dict, last: dict, names) -> dict[str, float]:
    """PDUs per second between two diagnostics, from their counts and reception stamps."""
    return {n: (int(last[f'rx/{n}']) - int(first[f'rx/{n}']))
            / (float(last[f'rx_stamp/{n}']) - float(first[f'rx_stamp/{n}'])) for n in names}


def _skip_if_the_machine_dropped(can_loop, summary: str) -> None:
    """Skip when every drop out of ACTIVE came where the machine delayed the link (a cycle late
    past the frame timeout by the CPU time the hypervisor or other tasks took, or the hypervisor
    taking the CPUs): the fixture ran once more and it happened again, so the loop cannot be
    judged here."""
    drops = _active_drops(can_loop.diags)
    machine = _machine_drops(can_loop)
    if drops and set(drops) <= set(machine):
        pytest.skip(f'the machine delayed the link where the bridge dropped, in both runs: '
                    f'{machine}; {summary}')


def _machine_drops(can_loop) -> dict[str, object]:
    """Drops out of ACTIVE the machine explains -> how: the late cycle that caused it (the car's
    for STATE_INVALID, the bridge's for HEARTBEAT) or the CPU time taken before it [ms]."""
    out = {r: f'{ms:.0f} ms taken' for r, ms in can_loop.taken.items() if ms >= TAKEN_MS}
    cause = {'STATE_INVALID': 'car', 'HEARTBEAT': 'bridge'}
    for reason, (a, b) in _drop_windows(can_loop.diags).items():
        late = [s for s in can_loop.stalls if s['machine'] and s['who'] == cause.get(reason)
                and a - 1.0 <= s['t'] <= b + 1.0]
        if late:
            out[reason] = late
    return out


def _faults(first: dict, last: dict) -> dict[str, int]:
    """Frames rejected and link errors between two diagnostics (their counts are totals)."""
    out = {k: int(v) - int(first.get(k, 0)) for k, v in last.items()
           if k.startswith(('rx_fault/', 'error/'))}
    return {k: n for k, n in out.items() if n}


def _active_drops(diags) -> dict[str, int]:
    """Drops to OFF out of an active mode, by reason (an ARMED bridge that drops while the car
    still starts is re-armed by auto_arm: it never requested anything)."""
    last = diags[-1] if diags else {}
    return {k.split('/')[-1]: int(v) for k, v in last.items()
            if k.startswith('drops/ACTIVE_')}


@pytest.mark.ros
@pytest.mark.slow
def test_can_loop_bus_and_bridge(can_loop):
    """Both directions every 10 ms, every PDU protected and checked, intact; requests reach the
    plant; any drop out of ACTIVE has its cause."""
    run, diags = can_loop.run, can_loop.diags
    truth, t = run.truth, run.truth['t']
    assert can_loop.wall < WALL_MAX_S - 1.0, \
        f'the simulated car did not end the run: {can_loop.wall:.1f} s'
    # one a second over the car's run (shorter than RUN_S where the link dropped before ACTIVE)
    assert len(diags) >= t[-1] - t[0] - 1.0, f'{len(diags)} bridge diagnostics'
    assert (len(t) - 1) / (t[-1] - t[0]) > 95.0, can_loop.timing

    # The link in operation: from the bridge's first second ACTIVE on. What happens before (the
    # nodes starting) is printed, not judged: a bridge still ARMED does not act on the car.
    first_active = next((k for k, d in enumerate(diags) if d['mode'] == 'ACTIVE_FULL'), None)
    if first_active is None:   # ACTIVE, then dropped within a second: no diagnostic saw it
        _skip_if_the_machine_dropped(can_loop, can_loop.timing)
    assert first_active is not None, f'never ACTIVE: {[d["mode"] for d in diags]}'
    live = diags[first_active:]
    live_car = [d for d in can_loop.car if d['_t'] >= live[0]['_t']]
    print('before the bridge was ACTIVE:', _faults({}, live[0]) or 'no faults')
    faults = _faults(live[0], live[-1])
    assert faults == {}, f'CRC/counter/range faults or bus errors: {faults}'
    # udp_multicast loops every datagram back to its sender: the bridge's own request frames are
    # its only "foreign" frames (within the one cycle still in flight when diagnostics are taken);
    # unicast UDP hands the bridge only the gateway's datagrams.
    for d in diags:
        own = sum(int(v) for k, v in d.items() if k.startswith('tx/')) \
            if can_loop.codec.description.kind != 'flexray' else 0
        assert 0 <= own - int(d['foreign_frames']) <= 6, f'foreign frames: {d}'
    state_pdus = list(can_loop.codec.state_frames)
    assert all(f'e2e/{name}' not in d for d in live for name in state_pdus), \
        'every state PDU E2E VALID while ACTIVE'
    # the state PDUs' rate from their reception stamps; a machine whose CPUs were taken from it
    # for 40 ms and more (all nodes stopped) cannot keep 100 per second: printed, not judged
    stamped = _stamped_rates(live[0], live[-1], state_pdus)
    rated = can_loop.taken_max < TAKEN_MS
    print(f'the machine took at most {can_loop.taken_max:.0f} ms of CPU in 100 ms'
          + ('' if rated else ': PDU rates not judged'))
    assert not rated or all(abs(hz - _pdu_hz(can_loop, n)) < 1.0 for n, hz in stamped.items()), \
        f'PDUs per second: {stamped}'
    # the car's end checks every request PDU the same way: nothing rejected, all VALID, 100 Hz
    from drift_vehicle_bridge.codec import COMMAND_FRAMES
    assert len(live_car) >= RUN_S - 2, f'{len(live_car)} car-side diagnostics'
    car_faults = _faults(live_car[0], live_car[-1])
    assert car_faults == {}, f'request PDUs rejected at the car: {car_faults}'
    assert not any(k.startswith('e2e/') for k in live_car[-1]), f'car side: {live_car[-1]}'
    car_rates = _stamped_rates(live_car[0], live_car[-1], COMMAND_FRAMES)
    assert not rated or all(99.0 < hz < 101.0 for hz in car_rates.values()), \
        f'at the car: {car_rates}'

    # what a drop out of ACTIVE ends (the time in ACTIVE, the state's validity then) is judged
    # only in a run the machine did not stall there: the bus checks above hold in any run
    _skip_if_the_machine_dropped(can_loop, can_loop.timing)
    assert all(d['validity'] == '0x7ff' for d in live), [d['validity'] for d in diags]
    active = [d for d in diags if d['mode'] == 'ACTIVE_FULL']
    modes = [d['mode'] for d in diags]
    # auto-armed from its first valid state on, and ACTIVE at the first command that asks for
    # full control (its next diagnostics, 1 s apart). When that command comes after the state
    # is valid is the graph's start-up (DDS discovery, the nodes' first cycles): printed
    first_valid = next(k for k, d in enumerate(diags) if d['validity'] == '0x7ff')
    assert modes[first_valid] in ('ARMED', 'ACTIVE_FULL'), f'not auto-armed: {modes}'
    full = run.command['t'][run.command['mode'] == int(Mode.FULL)]
    assert len(full), 'no command asked for full control'
    active_t = diags[first_active]['_t']
    print(f'start-up: state valid at {diags[first_valid]["_t"]:.2f} s, the first full-control '
          f'command at {full[0]:.2f} s, ACTIVE in the diagnostics of {active_t:.2f} s')
    assert active_t <= full[0] + 1.5, f'ACTIVE {active_t - full[0]:.2f} s after the first ' \
        f'full-control command: {modes}'
    assert len(active) >= 3, modes
    # Frame rates from totals over the diagnostics' stamps: rx_hz is (count - previous count) per
    # 1 s nominal, so its sum is the count (the diagnostics timer itself jitters under load).
    # Over the link in operation, as above: from the bridge's first second ACTIVE on (before,
    # the car may not send yet, and a start-up stall of the bridge is printed, not judged).
    span = live[-1]['_t'] - live[0]['_t']
    rates = {f'rx/{f}': sum(float(d[f'rx_hz/{f}']) for d in live[1:]) / span
             for f in state_pdus}
    expected = {f'rx/{f}': _pdu_hz(can_loop, f) for f in state_pdus}
    rates['tx/DS_CMD_STATUS'] = (int(live[-1]['tx/DS_CMD_STATUS'])
                                 - int(live[0]['tx/DS_CMD_STATUS'])) / span
    active_span = active[-1]['_t'] - active[0]['_t']
    rates.update({f'tx/{f}': (int(active[-1][f'tx/{f}']) - int(active[0][f'tx/{f}'])) / active_span
                  for f in ('DS_CMD_STEER', 'DS_CMD_TORQUE')})
    print('frames per second:', {k: round(float(v), 1) for k, v in rates.items()})
    assert not rated or all(0.95 < hz / expected.get(k, 100.0) < 1.05
                            for k, hz in rates.items()), \
        f'frames per second: {rates}'

    # The requests moved the plant: its steering follows the NMPC's command through the bus.
    from drift_tools.timeseries import resample
    on = (t > active[0]['_t']) & (t < active[-1]['_t'])
    delta_err = np.degrees(np.abs(truth['delta'] - resample(run.command, t, 'delta')))[on]
    assert np.median(delta_err) < 1.5, f'steering off the request by {np.median(delta_err):.2f} deg'

    # A drop to OFF out of ACTIVE must have its cause in the run: the car left the envelope, the
    # simulator or the bridge stalled longer than the frame timeout, or the machine's CPUs were
    # taken from it there. Anything else is a bridge, bus or controller fault.
    reasons = set(_active_drops(diags))
    env = load_bridge_params().mode.active_envelope
    outside = ~((truth['V'] >= env.V_min) & (truth['V'] <= env.V_max)
                & (np.abs(truth['beta']) <= env.beta_max) & (np.abs(truth['r']) <= env.r_max))
    machine = set(_machine_drops(can_loop))
    explained = {'ENVELOPE': bool(outside.any()),
                 'STATE_INVALID': can_loop.stall > STALL_S or 'STATE_INVALID' in machine,
                 'HEARTBEAT': can_loop.bridge_stall > STALL_S or 'HEARTBEAT' in machine}
    assert all(explained.get(r, False) for r in reasons), \
        f'unexplained drop to OFF: {reasons}; {can_loop.timing}; taken: {can_loop.taken} ms'


@pytest.mark.ros
@pytest.mark.slow
def test_can_loop_holds_the_drift(can_loop):
    """drift_hold_dry over the bus in real time: the 30 deg drift held, no spin, on the path.

    The grip-to-drift entry is left to the lock-step and one-process tests: in real time, with
    the two 10 ms CAN cycles on top of the plant's delays, 8 of 8 runs entered and 7 held (one
    bridge heartbeat trip on a 64 ms command pause): see the README's known limitations.
    """
    from drift_tools.timeseries import resample
    run, m = can_loop.run, can_loop.metrics
    truth, t = run.truth, run.truth['t']
    beta_deg = np.degrees(np.abs(truth['beta']))
    held = _longest_run(t, beta_deg > DRIFT_DEG)
    steady = t >= m['transient_end_s']
    e_y = resample(run.reference, t, 'e_y')[steady]
    e_y_rms = float(np.sqrt(np.mean(e_y ** 2))) if steady.any() else math.nan
    drops = _active_drops(can_loop.diags)
    # the two ways the controller has failed here, judged while the car still moved (V > 3 m/s):
    # torque requests jumping by most of the range every period, or braking into the drift
    moving = run.command['t'] < (t[np.argmax(truth['V'] < 3.0)] if (truth['V'] < 3.0).any()
                                 else np.inf)
    torque = run.command['drive_torque'][moving]
    chatter = float(np.mean(np.abs(np.diff(torque)) > 4000.0)) if len(torque) > 1 else math.nan
    braking = float(np.mean(torque < -1000.0)) if len(torque) else math.nan
    summary = (f'|beta| > {DRIFT_DEG:.0f} deg for {held:.1f} s, mean |beta| '
               f'{m["mean_abs_beta_steady_deg"]:.1f} deg from {m["transient_end_s"]:.1f} s, max '
               f'{beta_deg.max():.1f} deg; e_y rms {e_y_rms:.2f} m; min V after 3 s '
               f'{truth["V"][t > 3.0].min():.1f} m/s; bridge drops {sorted(set(drops))}; '
               f'NMPC torque while moving: jumps > 4000 Nm in {100 * chatter:.0f} % of periods, '
               f'< -1000 Nm in {100 * braking:.0f} %; '
               f'{can_loop.timing}')
    print(f'{can_loop.link} loop drift:', summary)
    _skip_if_the_machine_dropped(can_loop, summary)   # a drop in the first second ends it too
    assert beta_deg[t < 1.0].min() > 20.0, f'starts in the drift; {summary}'
    assert not drops, summary
    assert held > 8.0, summary
    assert beta_deg.max() < SPIN_DEG and not m['spun'], summary
    assert steady.sum() > 300 and 25.0 < m['mean_abs_beta_steady_deg'] < 35.0, summary
    # e_y is reported, not judged: in real time the NMPC's path tracking is far from its
    # lock-step quality (RMS 0.5-0.7 m lock-step, 1.3-6.4 m real time, ROS-only graph alike)
    # a drift, not a slide: counter-steer and drive torque (released: +10.6 deg, no torque)
    assert np.degrees(np.mean(truth['delta'][steady])) < -10.0, summary
    assert np.mean(truth['drive_torque'][steady]) > 500.0, summary
    # once running the NMPC never falls back; a reference late by a process schedule (real time,
    # a loaded machine) is bridged by the shifted plan, as designed, and must stay rare; after the
    # car ended the run, the states stop and the NMPC says so (stale), as it must
    st = run.status['t']
    status = run.status['status'][(st > 0.5) & (st <= t[-1])]
    status = status[np.argmax(status == 0):]   # running: from its first solution on
    assert np.all(status <= 1) and np.mean(status == 1) < 0.01, \
        f'NMPC statuses once running: {np.bincount(status.astype(int)).tolist()}'
