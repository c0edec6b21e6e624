"""The link probe: PDUs seen, their rates from the stamps, their E2E states, over UDP."""
import math
import socket

from drift_control.params import config_dir
from drift_control.signals import VehicleState
from drift_vehicle_bridge.codec import Codec
from drift_vehicle_bridge.pdu import Pdu
from drift_vehicle_bridge.probe import format_reports, probe
from drift_vehicle_bridge.soad import UdpTransport
from drift_vehicle_bridge.vehicle_side import CarSide


class Clock:
    """A clock the probe's loop advances: each receive takes 1 ms of it."""

    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


class Replayed:
    """A transport handing out PDUs stamped 10 ms apart, as a gateway's would arrive."""

    def __init__(self, pdus, clock):
        self.pdus, self.clock = list(pdus), clock

    def recv(self, timeout=0.0):
        self.clock.t += 0.001
        return self.pdus.pop(0) if self.pdus else None


def test_probe_names_rates_and_e2e_states_of_what_arrives(tmp_path):
    codec = Codec.load(config_dir() / 'flexray' / 'drift_vehicle.arxml')
    state = VehicleState(0.0, 8.0, -0.3, 0.6)
    pdus = []
    sent = []

    class Collect:
        def send(self, pdu):
            sent.append(pdu)

        def flush(self):
            pass

    car = CarSide(Collect(), codec)
    for k in range(100):
        sent.clear()
        car.send_state(state)
        pdus += [Pdu(p.id, p.data, timestamp=1.0 + 0.01 * k) for p in sent]
    yaw = codec.spec('DS_YAW').id
    bad = next(p for p in pdus if p.id == yaw)
    pdus.append(Pdu(yaw, bytes([bad.data[0] ^ 1]) + bad.data[1:], timestamp=2.0))   # bad CRC
    pdus.append(Pdu(0x7777, b'\x00' * 8, timestamp=2.0))                          # unknown
    clock = Clock()
    reports = {r.name: r for r in probe(Replayed(pdus, clock), codec, 2.0, clock=clock)}
    for name in set(codec.state_frames) - {'DS_YAW'}:
        r = reports[name]
        assert math.isclose(r.rate, 100.0, rel_tol=1e-6), r
        assert r.count == r.accepted == 100 and r.e2e == 'OK, VALID' and not r.faults, r
    assert reports['DS_YAW'].faults == {'crc': 1} and reports['DS_YAW'].e2e == 'ERROR (crc), INVALID'
    assert reports['?'].faults == {'unknown_id': 1}
    table = format_reports(list(reports.values()), codec)
    assert 'never seen: DS_CMD_STEER, DS_CMD_TORQUE, DS_CMD_STATUS' in table


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def test_probe_listens_on_a_udp_link():
    codec = Codec.load(config_dir() / 'flexray' / 'drift_vehicle.arxml')
    a, b = _free_port(), _free_port()
    with UdpTransport(('127.0.0.1', a), ('127.0.0.1', b)) as gateway, \
            UdpTransport(('127.0.0.1', b), ('127.0.0.1', a)) as listener:
        car = CarSide(gateway, codec)
        for _ in range(5):
            car.send_state(VehicleState(0.0, 8.0, -0.3, 0.6))
        reports = probe(listener, codec, 0.3)
    assert {r.name for r in reports} == set(codec.state_frames)
    assert all(r.count == 5 and r.accepted == 5 for r in reports), reports


def test_drift_probe_lists_a_gateway_s_pdus_and_exits_1_when_one_is_missing(capsys):
    """The operator's command on a UDP link, a simulated gateway sending from a thread."""
    import threading
    import time
    from drift_tools.operator import main
    codec = Codec.load(config_dir() / 'flexray' / 'drift_vehicle.arxml')
    ours, gateway = _free_port(), _free_port()
    args = ['probe', '--duration', '0.4', '--set', 'transport=udp', '--set',
            'description=flexray/drift_vehicle.arxml', '--set', f'udp.local=127.0.0.1:{ours}',
            '--set', f'udp.remote=127.0.0.1:{gateway}']

    def drive(stop, skip=()):   # until the probe has finished, however long it takes to start
        with UdpTransport(('127.0.0.1', gateway), ('127.0.0.1', ours)) as link:
            car = CarSide(link, codec)
            while not stop.is_set():
                car.send_state(VehicleState(0.0, 8.0, -0.3, 0.6), skip=skip)
                time.sleep(0.01)

    for skip, code in (((), 0), (('DS_YAW',), 1)):
        stop = threading.Event()
        sender = threading.Thread(target=drive, args=(stop, skip))
        sender.start()
        try:
            assert main(args) == code
        finally:
            stop.set()
            sender.join()
        out, err = capsys.readouterr()
        assert 'DS_VELOCITY' in out and 'OK, VALID' in out, out
        assert ('DS_YAW' in err) == bool(skip), err
    assert main(['probe', '--set', 'transport=flexray']) == 2
    assert 'bridge.transport' in capsys.readouterr().err
