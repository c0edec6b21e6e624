"""FlexRay ARXML description: the shipped file is the script's output, it mirrors the DBC's layouts
bit for bit under E2E profile 2, and every malformed input is a one-line ParamError."""
import random
import re

import cantools
import pytest
from autosar_data.abstraction import AutosarModelAbstraction, SystemCategory
from autosar_data.abstraction.communication import (
    EthernetCluster, FlexrayCluster, SocketConnectionIpduIdentifier)

from conftest import REPO, load_script
from drift_control.params import ParamError
from drift_vehicle_bridge.arxml import autosar_start, dbc_start, load_arxml
from drift_vehicle_bridge.description import COMMAND_SIGNALS, STATE_SIGNALS
from drift_vehicle_bridge.codec import load_description
from drift_vehicle_bridge.e2e import protection

DBC = REPO / 'config' / 'can' / 'drift_vehicle.dbc'
ARXML = REPO / 'config' / 'flexray' / 'drift_vehicle.arxml'
make_arxml = load_script('make_arxml')


@pytest.fixture(scope='module')
def dbc():
    return cantools.database.load_file(str(DBC))


@pytest.fixture(scope='module')
def description():
    return load_arxml(ARXML)


def test_the_shipped_arxml_is_a_fresh_run_of_the_script(tmp_path):
    out = tmp_path / 'drift_vehicle.arxml'
    assert make_arxml.main(['--out', str(out)]) == 0
    assert out.read_text() == ARXML.read_text(), \
        'config/flexray/drift_vehicle.arxml is stale: run scripts/make_arxml.py'


def test_autosar_data_alone_finds_every_signal_in_the_flexray_cluster():
    model = AutosarModelAbstraction.from_file(str(ARXML))
    clusters = list(model.find_system().clusters())
    flexray = [c for c in clusters if isinstance(c, FlexrayCluster)]
    assert [c.name for c in flexray] == ['DriftFlexRay']
    assert flexray[0].physical_channels.channel_b is None, 'channel A only'
    signals = {}
    for triggering in flexray[0].physical_channels.channel_a.frame_triggerings():
        for mapping in triggering.frame.mapped_pdus():
            signals[mapping.pdu.name] = {s.name for s in mapping.pdu.mapped_signals()}
    assert set(STATE_SIGNALS) <= set().union(*signals.values())
    for name, needed in COMMAND_SIGNALS.items():
        assert set(needed) <= signals[name], name
    assert any(isinstance(c, EthernetCluster) for c in clusters), 'Socket Adaptor header IDs'


def test_the_schedule_sends_every_pdu_every_10ms_on_channel_a(description):
    assert description.kind == 'flexray'
    slots = {}
    for spec in description.pdus:
        assert spec.cycle == pytest.approx(0.01), spec.name
        assert spec.bus['channel'] == 'A' and spec.bus['repetition'] == 2
        slots.setdefault((spec.bus['slot'], spec.bus['base_cycle']), set()).add(spec.bus['frame'])
        assert spec.fd is None
    assert all(len(frames) == 1 for frames in slots.values()), 'one frame per slot and cycle'
    frames = {s.bus['frame']: s.senders for s in description.pdus}
    assert frames['FR_DS_CMD'] == ('DRIFT_STACK',), 'the commands have a frame of their own'
    assert {frames[f] for f in frames if f != 'FR_DS_CMD'} == {('GATEWAY',)}


def test_layouts_and_ranges_equal_the_dbc(dbc, description):
    assert [s.name for s in description.pdus] == [m.name for m in dbc.messages]
    for spec in description.pdus:
        ours, theirs = spec.message, dbc.get_message_by_name(spec.name)
        assert spec.id == 0x00DF0000 + theirs.frame_id and spec.length == theirs.length == 8
        assert spec.senders == tuple(theirs.senders)
        for a, b in zip(ours.signals, theirs.signals, strict=True):
            fields = ('name', 'start', 'length', 'byte_order', 'is_signed', 'scale', 'offset',
                      'minimum', 'maximum', 'unit', 'choices')
            assert [getattr(a, f) for f in fields] == [getattr(b, f) for f in fields], a.name


def test_random_values_encoded_by_the_dbc_decode_the_same_from_the_arxml(dbc, description):
    rng = random.Random(25)
    for spec in description.pdus:
        theirs = dbc.get_message_by_name(spec.name)
        for _ in range(200):
            values = {s.name: _random_value(rng, s) for s in theirs.signals}
            data = theirs.encode(values, strict=True)
            assert spec.message.encode(values, strict=True) == data
            assert (spec.message.decode(data, decode_choices=False)
                    == theirs.decode(data, decode_choices=False))


def _random_value(rng, signal):
    """A raw value in the signal's [min|max], scaled: the values a sender can put on the bus."""
    lo = round((signal.minimum - signal.offset) / signal.scale)
    hi = round((signal.maximum - signal.offset) / signal.scale)
    return rng.randint(lo, hi) * signal.scale + signal.offset


def test_p02_protects_the_bits_of_the_dbc_crc_and_counter(dbc, description):
    data_ids = set()
    for spec in description.pdus:
        assert spec.e2e.profile == 'P02' and len(spec.e2e.data_id_list) == 16
        data_ids.update(spec.e2e.data_id_list)
        theirs = dbc.get_message_by_name(spec.name)
        header = {8 * (s.start // 8) + bit for s in theirs.signals
                  if s.name in ('CRC', 'AliveCounter') for bit in range(s.start % 8,
                                                                      s.start % 8 + s.length)}
        assert protection(spec.e2e, spec.length).header_bits == header, spec.name
    assert len(data_ids) == 16 * len(description.pdus), 'no data ID is used twice'


def test_load_description_reads_arxml_by_suffix():
    description = load_description(ARXML)
    assert description.kind == 'flexray'
    assert [(s.name, s.id) for s in description.pdus] == [
        (s.name, s.id) for s in load_arxml(ARXML).pdus]


# --- big-endian signals ------------------------------------------------------------------------

def test_start_bit_conversion_round_trips():
    for length in range(1, 33):
        for start in range(64):
            lsb = autosar_start(start, length, 'big_endian')
            assert dbc_start(lsb, length, 'big_endian') == start
    assert autosar_start(11, 12, 'big_endian') == 16       # MSB byte 1 bit 3 .. LSB byte 2 bit 0


def test_a_big_endian_signal_keeps_its_bytes(tmp_path):
    # delta_rate_req as a Motorola signal: MSB at byte 4 bit 7, LSB at byte 5 bit 0 (position 40).
    text = DBC.read_text().replace('delta_rate_req : 32|16@1-', 'delta_rate_req : 39|16@0-')
    arxml = _build(tmp_path, text)
    assert re.search(r'delta_rate_req</I-SIGNAL-REF>\s*<PACKING-BYTE-ORDER>MOST-SIGNIFICANT-BYTE-'
                     r'FIRST</PACKING-BYTE-ORDER>\s*<START-POSITION>40<', arxml.read_text())
    ours = _spec(load_arxml(arxml), 'DS_CMD_STEER').message
    theirs = cantools.database.load_string(text, 'dbc').get_message_by_name('DS_CMD_STEER')
    values = {'CRC': 0, 'AliveCounter': 0, 'steer_request': 1, 'delta_req': 0.0,
              'delta_rate_req': -1.234}
    assert ours.encode(values) == theirs.encode(values)
    assert ours.encode(values)[4:6] == (-1234).to_bytes(2, 'big', signed=True)


# --- malformed input: one line naming the file and the fault -----------------------------------

def _build(tmp_path, dbc_text: str):
    (tmp_path / 'in.dbc').write_text(dbc_text)
    out = tmp_path / 'out.arxml'
    make_arxml.build(tmp_path / 'in.dbc', out)
    return out


def _spec(description, name):
    return next(s for s in description.pdus if s.name == name)


def _edited(tmp_path, edit):
    """The shipped ARXML after ``edit(model)``, written to tmp_path."""
    model = AutosarModelAbstraction.from_file(str(ARXML))
    edit(model)
    path = tmp_path / 'edited.arxml'
    model.files()[0].filename = str(path)
    model.write()
    return path


def _error(path) -> str:
    with pytest.raises(ParamError) as err:
        load_arxml(path)
    message = str(err.value)
    assert '\n' not in message and message.startswith(str(path)), message
    return message


@pytest.mark.parametrize('text', ['', 'not xml at all', '<AUTOSAR><AR-PACKAGES>'])
def test_malformed_xml(tmp_path, text):
    path = tmp_path / 'bad.arxml'
    path.write_text(text)
    assert 'cannot read the ARXML' in _error(path)


def test_truncated_file_and_missing_file(tmp_path):
    path = tmp_path / 'cut.arxml'
    path.write_text(ARXML.read_text()[:len(ARXML.read_text()) // 2])
    assert 'cannot read the ARXML' in _error(path)
    assert 'cannot read the ARXML' in _error(tmp_path / 'absent.arxml')


def test_no_flexray_cluster(tmp_path):
    path = tmp_path / 'can_only.arxml'
    model = AutosarModelAbstraction.create(str(path))
    package = model.get_or_create_package('/Small')
    system = package.create_system('Small', SystemCategory.SystemDescription)
    system.create_can_cluster('Can', package).create_physical_channel('Can_Channel')
    model.write()
    assert 'no FLEXRAY-CLUSTER' in _error(path)


@pytest.mark.parametrize('signal, pdu', [('delta_req', 'DS_CMD_STEER'), ('vx', None),
                                         ('bridge_mode', 'DS_CMD_STATUS')])
def test_a_needed_signal_missing(tmp_path, signal, pdu):
    text = re.sub(rf'\b{signal}\b', f'{signal}_renamed', DBC.read_text())
    message = _error(_build(tmp_path, text))
    assert signal in message and (pdu is None or pdu in message), message


@pytest.mark.parametrize('name, expected', [
    ('PROFILE_22', 'E2E profile P22 is not supported'),     # AUTOSAR's, not the codec's
    ('PROFILE_44m', 'E2E profile P44m is not supported'),
    ('PROFILE_99', 'no profile autosar-data knows')])
def test_unsupported_e2e_profile(tmp_path, name, expected):
    path = tmp_path / 'profile.arxml'
    path.write_text(ARXML.read_text().replace('>PROFILE_02<', f'>{name}<'))
    assert expected in _error(path)


def test_a_p02_data_id_list_that_is_not_16_bytes(tmp_path):
    path = tmp_path / 'ids.arxml'
    path.write_text(ARXML.read_text().replace('<DATA-ID>0</DATA-ID>', '', 1))
    assert 'DS_VELOCITY' in _error(path)


def test_a_pdu_without_e2e_protection(tmp_path):
    def drop_transformer(model):
        group = model.get_element_by_path('/DriftVehicle/SignalGroups/DS_YAW')
        group.remove_sub_element_kind('COM-BASED-SIGNAL-GROUP-TRANSFORMATIONS')
    assert 'DS_YAW: no E2E protection' in _error(_edited(tmp_path, drop_transformer))


def test_a_pdu_without_header_id(tmp_path):
    def drop_identifier(model):
        for _, element in model.model.elements_dfs:
            if element.element_name == 'SOCKET-CONNECTION-IPDU-IDENTIFIER':
                ident = SocketConnectionIpduIdentifier(element)
                if ident.pdu_triggering.pdu.name == 'DS_POSE_YAW':
                    element.parent.remove_sub_element(element)
                    return
    assert 'DS_POSE_YAW: no Socket Adaptor header ID' in _error(_edited(tmp_path,
                                                                         drop_identifier))


def test_the_script_reports_a_bad_dbc_in_one_line(tmp_path, capsys):
    (tmp_path / 'in.dbc').write_text(DBC.read_text().replace('BO_ 386 DS_CMD_STATUS',
                                                             'BO_ 386 DS_CMD_STATE'))
    assert make_arxml.main(['--dbc', str(tmp_path / 'in.dbc'),
                            '--out', str(tmp_path / 'out.arxml')]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and 'DS_CMD_STATE' in err
