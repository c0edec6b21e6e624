"""MDF4 out and in: a bag exported opens in asammdf with units and the bag's values and log times;
an export and a car logger's CAN (FD) bus logging, decoded with the DBC, read back as a run."""
import hashlib
import json
import re
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, load_script
from drift_tools.bag import read_bag
from drift_tools.mdf import read_mdf
from drift_tools.operator import main as drift
from drift_tools.replay import iter_raw
from drift_tools.run_info import RECORD_NAME
from test_tools_bag import T0, encoder, write_run

asammdf = pytest.importorskip('asammdf')
can = pytest.importorskip('can')
cantools = pytest.importorskip('cantools')

RUN = {'scenario': 'drift_hold_dry', 'vehicle': 'gr86', 'seed': '7', 'overrides': '[]',
       'clock': 'lockstep', 'commit': 'c0ffee' * 6 + 'c0ff', 'dirty': 'false',
       'config': json.dumps({'defaults.yaml': 'x: 1\n'})}
DBCS = [p for p in ('drift_vehicle_fd.dbc', 'drift_vehicle.dbc')
        if (REPO / 'config' / 'can' / p).exists()]


def command(i):
    return {'header': {'stamp': {'sec': i, 'nanosec': 0}}, 'mode': i % 4, 'delta': -0.001 * i,
            'delta_rate': 0.5, 'drive_torque': 10.0 * i}


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    """States (arrays, a bool, stamps, a string), NMPC status (an enum, a string, sequences),
    commands, a path (a sequence only) and the run record: every kind of field once."""
    bag_dir = tmp_path_factory.mktemp('mdf') / 'bag'
    w = write_run(bag_dir, 120)
    w.add_metadata(RECORD_NAME, RUN)
    w.add_topic('/drift/command', 'drift_msgs/msg/DriftCommand')
    w.add_topic('/drift/path', 'nav_msgs/msg/Path', latched=True)
    enc = encoder('drift_msgs/msg/DriftCommand')
    for i in range(60):
        w.write('/drift/command', enc(command(i)), T0 + i * 2 * 10**7 + 2)
    w.write('/drift/path', encoder('nav_msgs/msg/Path')({'header': {'frame_id': 'map'}}), T0 + 3)
    w.close()
    return bag_dir


@pytest.fixture(scope='module')
def exported(bag):
    out = bag.with_name('run.mf4')
    assert drift(['bag', 'export', str(bag), str(out)]) == 0
    return out


def field(msg, channel: str):
    """The value a channel (``vehicle/state.wheel_speeds[2]``) holds, from a decoded message."""
    for name, index in re.findall(r'(\w+)(?:\[(\d+)\])?', channel.split('.', 1)[1]):
        msg = getattr(msg, name)
        if index:
            msg = msg[int(index)]
    return msg


def test_every_channel_holds_the_bags_values_and_log_times(bag, exported):
    mdf = asammdf.MDF(exported)
    t0 = int(mdf.header.abs_time)
    raw = {}
    for m in iter_raw(bag):
        raw.setdefault(m.topic, []).append(m.t_ns)
    assert t0 == min(t[0] for t in raw.values()), 'start time: the first log time to the ns'
    decoded = read_bag(bag, backend='mcap')       # mcap_ros2: another decoder than the export's
    groups = {g.channel_group.acq_name: i for i, g in enumerate(mdf.groups)}
    assert set(groups) == set(decoded)
    checked = 0
    for topic, index in groups.items():
        msgs = decoded[topic]
        master = mdf.get_master(index)
        assert (np.round(master * 1e9).astype(np.int64) + t0).tolist() == raw[topic]
        for j, channel in enumerate(mdf.groups[index].channels):
            if j == mdf.masters_db[index]:
                continue
            assert channel.name.startswith(topic.strip('/') + '.')
            samples = mdf.get(group=index, index=j, raw=True).samples
            got = [s.decode() if isinstance(s, bytes) else s for s in samples.tolist()]
            assert got == [field(m.msg, channel.name) for m in msgs], channel.name
            checked += 1
    assert checked == 22 + 10 + 7 + 3, 'every fixed-size field of the four topics'
    mdf.close()


def test_units_come_from_the_message_definitions(exported):
    mdf = asammdf.MDF(exported)
    units = {c.name: c.unit for g in mdf.groups for c in g.channels}
    assert units['vehicle/state.v'] == 'm/s' and units['vehicle/state.ax'] == 'm/s^2'
    assert units['vehicle/state.wheel_speeds[3]'] == 'rad/s'
    assert units['drift/command.drive_torque'] == 'Nm' and units['drift/command.delta'] == 'rad'
    assert units['drift/nmpc/status.solve_time'] == 's'
    assert units['vehicle/state.header.stamp.sec'] == 's'
    assert units['vehicle/state.validity'] == ''
    assert mdf.get('vehicle/state.v').comment == 'speed over ground [m/s]'
    assert mdf.get('drift/command.mode').samples[:4].tolist() == [b'OFF', b'FULL',
                                                                   b'TORQUE_ONLY', b'FALLBACK']
    mdf.close()


def test_the_header_keeps_the_run_and_the_bag_is_not_written(bag, exported):
    mdf = asammdf.MDF(exported)
    comment = mdf.header.comment
    for value in ('drift_hold_dry', 'gr86', '>7<', RUN['commit'], 'sim time'):
        assert value in comment
    assert 'defaults.yaml' not in comment, 'the configuration is attached, not in the comment'
    names = [Path(str(a.file_name)).name for a in mdf.attachments]
    record = json.loads(bytes(mdf.extract_attachment(names.index('drift_run.json'))[0]))
    assert record == RUN
    assert any('drift bag export' in fh.comment for fh in mdf.file_history)
    mdf.close()
    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in bag.iterdir()}
    assert drift(['bag', 'export', str(bag), str(bag.with_name('again.mdf')),
                  '--topics', '/drift/command']) == 0
    assert {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in bag.iterdir()} == before


def test_an_unfinished_bag_exports_what_is_intact(tmp_path):
    from test_bag_salvage import chunk_offsets
    write_run(tmp_path / 'bag', 200, chunk_size=2048).close()
    mcap = next((tmp_path / 'bag').glob('*.mcap'))
    mcap.write_bytes(mcap.read_bytes()[:chunk_offsets(mcap)[-1]])   # as after a SIGKILL
    before = mcap.read_bytes()
    assert drift(['bag', 'export', str(tmp_path / 'bag'), str(tmp_path / 'x.mf4')]) == 0
    assert mcap.read_bytes() == before
    states = read_bag(tmp_path / 'bag')['/vehicle/state']
    mdf = asammdf.MDF(tmp_path / 'x.mf4')
    assert mdf.get('vehicle/state.v').samples.tolist() == [m.msg.v for m in states]
    assert 0 < len(states) < 200
    mdf.close()


def test_an_export_reads_back_as_the_bag(bag, exported):
    back, orig = read_mdf(exported), read_bag(bag, backend='mcap')
    assert set(back) == set(orig)
    for topic, msgs in orig.items():
        assert [m.t for m in back[topic]] == pytest.approx([m.t for m in msgs], abs=1e-9)
    s, o = back['/vehicle/state'][7].msg, orig['/vehicle/state'][7].msg
    assert (s.v, s.beta, list(s.wheel_speeds), s.header.frame_id) == \
        (o.v, o.beta, list(o.wheel_speeds), o.header.frame_id)
    status = back['/drift/nmpc/status'][3].msg
    assert (status.status, status.message, status.predicted_states) == (2, 'it 6', [])


def test_a_report_from_the_export_is_the_bags(tmp_path):
    synthetic_bag = pytest.importorskip('test_report').synthetic_bag
    bag = synthetic_bag(tmp_path / 'run')
    assert drift(['bag', 'export', str(bag), str(tmp_path / 'run.mf4')]) == 0
    report = load_script('report')
    assert report.main([str(bag), '--out', str(tmp_path / 'a'), '--no-figures']) == 0
    assert report.main([str(tmp_path / 'run.mf4'), '--out', str(tmp_path / 'b'),
                        '--no-figures']) == 0
    a, b = (json.loads((tmp_path / d / 'metrics.json').read_text()) for d in 'ab')
    assert a == b and a['nmpc_cycles'] == 1000


# --- a car logger's CAN / CAN FD bus logging -----------------------------------------------------

def write_can_log(path, dbc: Path, cycles: int = 150):
    """python-can's MF4Writer logging every state frame of ``dbc`` each 10 ms, the sideslip's
    frame last in its cycle, plus the command frames; returns the decoded state per cycle."""
    db = cantools.database.load_file(dbc)
    states = [m for m in db.messages if 'GATEWAY' in m.senders]
    states.sort(key=lambda m: any(s.name == 'beta' for s in m.signals))
    writer, t_start = can.io.MF4Writer(path), time.time()
    sent = []
    for k in range(cycles):
        values = {}
        for j, message in enumerate(states + [m for m in db.messages if m not in states]):
            raw = {s.name: s.minimum + (s.maximum - s.minimum) * (0.5 + 0.4 * np.sin(0.05 * k + i))
                   if s.unit else 0 for i, s in enumerate(message.signals)}   # E2E fields: 0
            data = message.encode(raw, strict=False)
            writer.on_message_received(can.Message(
                timestamp=t_start + 0.01 * k + 1e-4 * j, arbitration_id=message.frame_id,
                is_extended_id=message.is_extended_frame, data=data, is_fd=message.is_fd,
                bitrate_switch=message.is_fd, channel=0))
            if message in states:
                values.update(message.decode(data, decode_choices=False))
        sent.append((0.01 * k + 1e-4 * (len(states) - 1), values))
    writer.stop()
    return sent


@pytest.mark.parametrize('dbc_name', DBCS)
def test_a_can_log_decodes_with_the_dbc_into_the_state(tmp_path, dbc_name):
    from drift_vehicle_bridge.codec import WHEELS
    dbc = REPO / 'config' / 'can' / dbc_name
    sent = write_can_log(tmp_path / 'car.mf4', dbc)
    raw = asammdf.MDF(tmp_path / 'car.mf4')
    assert 'CAN_DataFrame' in raw.channels_db
    assert raw.get('CAN_DataFrame.EDL').samples.any() == dbc_name.endswith('_fd.dbc')
    raw.close()
    states = read_mdf(tmp_path / 'car.mf4', dbc)['/vehicle/state']
    assert len(states) == len(sent)
    t0 = states[0].t
    for m, (t, values) in zip(states, sent):
        assert m.t - t0 == pytest.approx(t - sent[0][0], abs=2e-6)
        s = m.msg
        assert (s.v, s.beta, s.r, s.delta, s.drive_torque, s.x, s.yaw) == pytest.approx(
            (values['V'], values['beta'], values['r'], values['delta'], values['drive_torque'],
             values['x'], values['yaw']), abs=1e-12)
        assert s.wheel_speeds == pytest.approx([values[w] for w in WHEELS], abs=1e-12)
        assert m.msg.header.stamp.sec + 1e-9 * m.msg.header.stamp.nanosec == pytest.approx(m.t)
    report = load_script('report')
    assert report.main([str(tmp_path / 'car.mf4'), '--dbc', str(dbc), '--no-figures']) == 0
    assert (tmp_path / 'car_report' / 'metrics.json').exists()


# --- bad input: one line, exit 2 -----------------------------------------------------------------

def mdf_with(path, version='4.10', **channels):
    mdf = asammdf.MDF(version=version)
    t = np.arange(10) * 0.01
    mdf.append([asammdf.Signal(np.ones(10), t, name=n) for n in channels or ('foo',)])
    mdf.save(path, overwrite=True)
    mdf.close()
    return path


@pytest.mark.parametrize('make, says', [
    (lambda d: (d / 'x.mf4').write_text('not a measurement') and d / 'x.mf4', 'not an MDF4 file'),
    (lambda d: (d / 'x.mf4').write_bytes(b'') or d / 'x.mf4', 'not an MDF4 file'),
    (lambda d: mdf_with(d / 'x.mdf', '3.30'), 'MDF 3.30, not MDF4'),
    (lambda d: (d / 'x.mf4').write_bytes(mdf_with(d / 'y.mf4').read_bytes()[:300]) and
     d / 'x.mf4', 'unreadable MDF4 file'),
    (lambda d: mdf_with(d / 'x.mf4', V=1, r=1), 'no channel beta'),
    (lambda d: (write_can_log(d / 'x.mf4', REPO / 'config' / 'can' / DBCS[0], 3), d / 'x.mf4')[1],
     'CAN bus logging; give the DBC'),
])
def test_report_on_a_bad_mdf4_file_is_one_line_and_exit_2(tmp_path, capfd, make, says):
    path = make(tmp_path)
    assert load_script('report').main([str(path), '--no-figures']) == 2
    err = capfd.readouterr().err.strip()
    assert says in err and len(err.splitlines()) == 1, err


def test_a_cut_file_leaves_no_destructor_complaint_for_later(tmp_path, monkeypatch):
    import gc
    import sys
    from drift_tools.mdf import MdfError, open_mdf
    complaints = []
    monkeypatch.setattr(sys, 'unraisablehook', complaints.append)
    cut = tmp_path / 'x.mf4'
    cut.write_bytes(mdf_with(tmp_path / 'y.mf4').read_bytes()[:300])
    with pytest.raises(MdfError, match='unreadable MDF4 file'):
        open_mdf(cut)
    gc.collect()   # the half-read reader, if still alive, complains here
    assert complaints == []


def test_a_dbc_that_decodes_nothing_names_the_missing_channels(tmp_path, capfd):
    write_can_log(tmp_path / 'x.mf4', REPO / 'config' / 'can' / DBCS[0], 3)
    other = REPO / 'config' / 'can' / 'drift_vehicle.dbc'
    if DBCS[0] == other.name:
        pytest.skip('only the classic DBC is here')
    assert load_script('report').main([str(tmp_path / 'x.mf4'), '--dbc', str(other)]) == 2
    err = capfd.readouterr().err.strip()
    assert 'no channel V, beta, r' in err and 'drift_vehicle.dbc' in err
    assert len(err.splitlines()) == 1, err


def test_export_refuses_an_existing_file_and_a_missing_bag(bag, exported, tmp_path, capfd):
    assert drift(['bag', 'export', str(bag), str(exported)]) == 2
    assert drift(['bag', 'export', str(tmp_path / 'nope'), str(tmp_path / 'x.mf4')]) == 2
    assert drift(['bag', 'export', str(bag), str(tmp_path / 'y'), '--format', 'mdf4',
                  '--topics', '/nope']) == 2
    err = capfd.readouterr().err
    assert 'exists' in err and 'no such bag directory' in err and "no messages on ['/nope']" in err
    assert len(err.strip().splitlines()) == 3 and 'Traceback' not in err
