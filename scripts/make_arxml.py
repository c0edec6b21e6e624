#!/usr/bin/env python3
"""Write the FlexRay ARXML of the drift stack's vehicle interface from the classic CAN DBC.

    .venv/bin/python scripts/make_arxml.py              # writes config/flexray/drift_vehicle.arxml
    .venv/bin/python scripts/make_arxml.py --out /tmp/drift_vehicle.arxml

This script is the source of truth of the ARXML (tests/test_arxml.py checks that the shipped file
equals a fresh run): edit the DBC or the tables below, then run it again. The file (AUTOSAR R4.4.0,
schema AUTOSAR_00046, written with autosar-data) holds:

- the DBC's twelve PDUs, 8 bytes each, with the same signals: names, start bits, lengths, byte
  order, signedness (SW-BASE-TYPE), scale and offset (COMPU-METHOD), unit, [min|max]
  (DATA-CONSTR), value tables (TEXTTABLE) and comments (DESC);
- E2E profile 2 per PDU (an E2E transformer on the PDU's I-SIGNAL-GROUP): CRC in byte 0 and the
  counter in the low nibble of byte 1, the bits of the DBC's CRC and AliveCounter signals, with a
  data ID list of 16 bytes per PDU (``p02_data_ids``);
- a FlexRay cluster, channel A only, 5 ms communication cycle: four 32-byte frames in the static
  segment, each sent every second cycle (cycle repetition 2, i.e. every 10 ms), three PDUs per
  frame with an update bit each (``FRAMES``);
- an Ethernet cluster with one UDP socket connection between the gateway and the stack whose
  SOCKET-CONNECTION-IPDU-IDENTIFIERs give each PDU its Socket Adaptor header ID
  (``HEADER_ID_BASE`` + the DBC's CAN id).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import NamedTuple

import cantools
from autosar_data import AutosarVersion
from autosar_data.abstraction import AutosarModelAbstraction, ByteOrder, SystemCategory
from autosar_data.abstraction.communication import (
    CommunicationDirection, CycleRepetition, E2EProfile, E2ETransformationTechnologyConfig,
    FlexrayChannelName, FlexrayClusterSettings, FlexrayCommunicationCycle, IPv4AddressSource,
    NetworkEndpointAddress, SocketAddressType, TpConfig)
from autosar_data.abstraction.datatype import (
    BaseTypeEncoding, CompuMethodContent, CompuScaleDirection, DataConstrType, TextTableEntry)

from drift_control.cli_args import output_problem
from drift_control.params import ParamError
from drift_vehicle_bridge.arxml import autosar_start

REPO = Path(__file__).resolve().parents[1]
DBC = REPO / 'config' / 'can' / 'drift_vehicle.dbc'
OUT = REPO / 'config' / 'flexray' / 'drift_vehicle.arxml'
VERSION = AutosarVersion.AUTOSAR_00046        # R4.4.0: still has SOCKET-CONNECTION-BUNDLE
ROOT = '/DriftVehicle'
STATE_SENDER, COMMAND_SENDER = 'GATEWAY', 'DRIFT_STACK'


class FrameSlot(NamedTuple):
    """One FlexRay frame of the static segment and the PDUs it carries, in this order."""

    name: str
    slot: int
    base_cycle: int
    pdus: tuple[str, ...]


# FlexRay schedule. autosar-data's default cluster (FlexrayClusterSettings(): 10 Mbit/s, 5 ms
# cycle, 50 static slots of 62 us) and a cycle repetition of 2 send every frame every 10 ms, the
# DBC's GenMsgCycleTime. Two state frames share slot 10 in alternate cycles (base cycle 0 and 1):
# static slots are the scarce resource. The commands have a frame of their own (the stack is its
# only sender). Channel B stays unused: E2E and the bridge's timeouts, not channel redundancy,
# guard the interface.
CYCLE_REPETITION, REPETITION = CycleRepetition.C2, 2
FRAMES = (
    FrameSlot('FR_DS_STATE_1', 10, 0, ('DS_VELOCITY', 'DS_YAW', 'DS_ACCEL')),
    FrameSlot('FR_DS_STATE_2', 10, 1, ('DS_WHEELS_FRONT', 'DS_WHEELS_REAR', 'DS_STEERING')),
    FrameSlot('FR_DS_STATE_3', 11, 0, ('DS_POWERTRAIN', 'DS_POSE_XY', 'DS_POSE_YAW')),
    FrameSlot('FR_DS_CMD', 20, 1, ('DS_CMD_STEER', 'DS_CMD_TORQUE', 'DS_CMD_STATUS')),
)
FRAME_LENGTH = 32        # bytes: three 8-byte PDUs, their update bits in byte 24, room for a 4th
UPDATE_BIT_BYTE = 24

# Socket Adaptor header ID = HEADER_ID_BASE + the PDU's CAN id in the DBC: a trace shows the
# familiar id in the low 16 bits, and no header ID is a valid 11-bit CAN id.
HEADER_ID_BASE = 0x00DF0000
GATEWAY_UDP = ('192.168.25.1', 30502)    # example addresses; the ports match config/bridge.yaml
STACK_UDP = ('192.168.25.2', 30501)

# E2E supervision as config/bridge.yaml (monitor.max_counter_delta, monitor.e2e); no new data
# for 3 cycles is its monitor.frame_timeout (30 ms).
E2E_SUPERVISION = dict(max_delta_counter=2, window_size=3, min_ok_state_init=2,
                       max_error_state_init=0, min_ok_state_valid=1, max_error_state_valid=0,
                       min_ok_state_invalid=2, max_error_state_invalid=0,
                       max_no_new_or_repeated_data=3)

# DBC unit -> AUTOSAR UNIT short name (a short name allows no '/'); DISPLAY-NAME keeps the text.
UNIT_NAMES = {'m/s': 'MeterPerSecond', 'm/s^2': 'MeterPerSecondSquared', 'rad': 'Radian',
              'rad/s': 'RadianPerSecond', 'Nm': 'NewtonMeter', 'm': 'Meter'}
E2E_SIGNALS = {
    'CRC': 'E2E profile 2 CRC8H2F (AUTOSAR Crc_CalculateCRC8H2F, polynomial 0x2F) over bytes '
           '1..7, then the data ID that the counter selects from the PDU\'s data ID list.',
    'AliveCounter': 'E2E profile 2 counter 0..15 in the low nibble of byte 1, +1 per PDU; it '
                    'indexes the data ID list.',
}


def p02_data_ids(index: int) -> list[int]:
    """E2E P02 data ID list of the PDU at ``index`` (0..15) in the DBC: 16 * counter + index.

    For every counter value the twelve PDUs use twelve different data IDs and no two entries
    repeat anywhere, so a PDU protected for another PDU's slot never passes (AUTOSAR PRS E2E
    Protocol, profile 2: the data ID of each counter value comes from a list of 16 bytes).
    """
    if not 0 <= index < 16:
        raise ParamError(f'p02_data_ids: PDU index {index} outside 0..15')
    return [16 * counter + index for counter in range(16)]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--dbc', default=str(DBC), help='classic CAN DBC to mirror')
    parser.add_argument('--out', default=str(OUT), help='ARXML file to write')
    args = parser.parse_args(argv)
    problem = output_problem(args.out, [args.dbc])
    if problem is not None:
        print(f'make_arxml: {problem}', file=sys.stderr)
        return 2
    try:
        build(args.dbc, args.out)
    except (ParamError, OSError) as err:
        print(f'make_arxml: {_one_line(err)}', file=sys.stderr)
        return 2
    print(f'wrote {args.out}')
    return 0


def build(dbc_path, out_path) -> None:
    """Write the ARXML for the DBC at ``dbc_path`` to ``out_path``."""
    try:
        db = cantools.database.load_file(str(dbc_path), database_format='dbc')
    except cantools.database.UnsupportedDatabaseFormatError as err:
        raise ParamError(f'{dbc_path}: cannot read the DBC: {_one_line(err)}') from None
    messages = {m.name: m for m in db.messages}
    scheduled = [name for frame in FRAMES for name in frame.pdus]
    if sorted(scheduled) != sorted(messages):
        raise ParamError(f'{dbc_path}: its messages {sorted(messages)} differ from the FlexRay '
                         f'schedule\'s PDUs {sorted(scheduled)}')
    Path(out_path).parent.mkdir(parents=True, exist_ok=True)
    model = AutosarModelAbstraction.create(str(out_path), version=VERSION)
    model.root_element.comment = (
        f' Generated by scripts/make_arxml.py from {_display(dbc_path)}: do not edit, run the '
        'script. FlexRay PDUs of the drift stack <-> vehicle gateway interface, E2E profile 2, '
        'Socket Adaptor header IDs for an Ethernet gateway. ')
    writer = _Writer(model, db)
    for index, message in enumerate(db.messages):
        writer.pdu(message, index)
    writer.flexray()
    writer.ethernet()
    model.write()


class _Writer:
    """Adds the interface's elements to an autosar-data model, package by package."""

    def __init__(self, model: AutosarModelAbstraction, db):
        self.model, self.db = model, db
        self.pkg = {name: model.get_or_create_package(f'{ROOT}/{name}') for name in (
            'System', 'Topology', 'Ecus', 'Frames', 'Pdus', 'SignalGroups', 'SystemSignalGroups',
            'Units', 'BaseTypes', 'Transformers')}
        self.system = self.pkg['System'].create_system('DriftVehicle',
                                                       SystemCategory.SystemDescription)
        _describe(self.system.element, 'Drift stack <-> vehicle gateway interface: the PDUs of '
                  'the classic CAN DBC as FlexRay PDUs, same signals, SI units, radians. GATEWAY '
                  'sends the vehicle state, DRIFT_STACK the commands (DS_CMD_*).')
        self.ecus = {name: self.system.create_ecu_instance(name, self.pkg['Ecus'])
                     for name in (STATE_SENDER, COMMAND_SENDER)}
        for node in db.nodes:
            if node.name in self.ecus:
                _describe(self.ecus[node.name].element, node.comment)
        self.units, self.base_types, self.pdus, self.senders = {}, {}, {}, {}
        dts = self.pkg['Transformers'].create_data_transformation_set('DriftE2E')
        config = E2ETransformationTechnologyConfig(
            profile=E2EProfile.P02, zero_header_length=True, transform_in_place=True, offset=0,
            **E2E_SUPERVISION)
        self.e2e = dts.create_transformation_technology('E2E_P02', config)
        _describe(self.e2e.element, 'AUTOSAR E2E profile 2 inside the PDU (header length 0, in '
                  'place, offset 0): CRC byte 0, counter bits 8..11. Supervision as '
                  'config/bridge.yaml monitor (max_counter_delta, e2e).')
        self.chain = dts.create_data_transformation('E2E_P02_COM', [self.e2e], True)

    # --- PDUs and signals --------------------------------------------------------------------

    def pdu(self, message, index: int) -> None:
        """The message as an I-SIGNAL-I-PDU, its signals in an E2E-protected I-SIGNAL-GROUP."""
        name = message.name
        pdu = self.system.create_isignal_ipdu(name, self.pkg['Pdus'], message.length)
        if message.comment:
            _describe(pdu.element, message.comment)
        sys_group = self.pkg['SystemSignalGroups'].create_system_signal_group(name)
        group = self.system.create_isignal_group(name, self.pkg['SignalGroups'], sys_group)
        pdu.map_signal_group(group)
        sig_pkg = self._package('ISignals', name)
        sys_pkg = self._package('SystemSignals', name)
        for signal in message.signals:
            system_signal = sys_pkg.create_system_signal(signal.name)
            self._physical(system_signal, signal, name)
            isignal = self.system.create_isignal(
                signal.name, sig_pkg, signal.length, system_signal,
                datatype=self._base_type(signal.length, signal.is_signed))
            _describe(isignal.element, E2E_SIGNALS.get(signal.name) or signal.comment)
            sys_group.add_signal(system_signal)
            group.add_signal(isignal)
            byte_order = (ByteOrder.MostSignificantByteLast if signal.byte_order == 'little_endian'
                          else ByteOrder.MostSignificantByteFirst)
            pdu.map_signal(isignal, autosar_start(signal.start, signal.length, signal.byte_order),
                           byte_order)
        group.add_data_transformation(self.chain)
        props = group.create_e2e_transformation_isignal_props(self.e2e)
        props.data_ids = p02_data_ids(index)
        props.data_length = 8 * message.length
        self.pdus[name] = pdu
        self.senders[name] = tuple(message.senders)

    def _physical(self, system_signal, signal, pdu_name: str) -> None:
        """Scale, offset or value table (COMPU-METHOD), unit and [min|max] of a signal."""
        cm_pkg = self._package('CompuMethods', pdu_name)
        choices = signal.conversion.choices
        if choices:
            content = CompuMethodContent.TextTable(texts=[
                TextTableEntry(text=str(text), value=float(value))
                for value, text in sorted(choices.items())])
        elif signal.scale == 1 and signal.offset == 0:
            content = CompuMethodContent.Identical()
        else:
            content = CompuMethodContent.Linear(
                direction=CompuScaleDirection.IntToPhys, factor=float(signal.scale),
                offset=float(signal.offset), divisor=1.0)
        system_signal.compu_method = cm_pkg.create_compu_method(signal.name, content)
        if signal.unit:
            system_signal.unit = self._unit(signal.unit)
        if signal.minimum is not None and signal.maximum is not None:
            constr = self._package('DataConstrs', pdu_name).create_data_constr(signal.name)
            # A value table's physical values are texts: its limits are internal (raw) values.
            kind = DataConstrType.Internal if choices else DataConstrType.Physical
            constr.create_data_constr_rule(kind, lower_limit=float(signal.minimum),
                                           upper_limit=float(signal.maximum))
            system_signal.data_constr = constr

    def _unit(self, text: str):
        if text not in self.units:
            name = UNIT_NAMES.get(text) or ''.join(c if c.isalnum() else '_' for c in text)
            self.units[text] = self.pkg['Units'].create_unit(name, display_name=text)
        return self.units[text]

    def _base_type(self, length: int, signed: bool):
        name = f'{"sint" if signed else "uint"}{length}'
        if name not in self.base_types:
            encoding = BaseTypeEncoding.TwosComplement if signed else BaseTypeEncoding.NoEncoding
            self.base_types[name] = self.pkg['BaseTypes'].create_sw_base_type(name, length,
                                                                               encoding)
        return self.base_types[name]

    def _package(self, kind: str, pdu_name: str):
        """``/DriftVehicle/<kind>/<PDU>``: short names are unique per package, and every PDU has
        its ``CRC`` and ``AliveCounter`` signals, named as in the DBC."""
        return self.model.get_or_create_package(f'{ROOT}/{kind}/{pdu_name}')

    # --- FlexRay -------------------------------------------------------------------------------

    def flexray(self) -> None:
        """Cluster, channel A, both ECUs on it, the frames in their static slots."""
        settings = FlexrayClusterSettings()
        settings.payload_length_static = FRAME_LENGTH // 2      # in 2-byte words
        frame_time = frame_duration(settings)
        slot_time = settings.static_slot_duration * settings.macrotick_duration
        if not settings.verify() or frame_time > slot_time:
            raise ParamError(f'make_arxml: FlexRay settings do not verify or a frame '
                             f'({1e6 * frame_time:.1f} us) overruns its slot')
        cluster = self.system.create_flexray_cluster('DriftFlexRay', self.pkg['Topology'],
                                                     settings)
        _describe(cluster.element, f'FlexRay {settings.baudrate / 1e6:g} Mbit/s, '
                  f'{1000 * settings.cycle:g} ms communication cycle, channel A only. Every '
                  f'frame is static with cycle repetition {REPETITION}: each PDU every '
                  f'{1000 * REPETITION * settings.cycle:g} ms, the DBC\'s cycle time. A '
                  f'{FRAME_LENGTH}-byte frame takes {1e6 * frame_time:.1f} us of its '
                  f'{1e6 * slot_time:g} us static slot.')
        channel = cluster.create_physical_channel('DriftFlexRay_A', FlexrayChannelName.A)
        for name, ecu in self.ecus.items():
            controller = ecu.create_flexray_communication_controller(f'{name}_FlexRay')
            controller.connect_physical_channel(f'{name}_FlexRayConnector_A', channel)
        for spec in FRAMES:
            frame = self.system.create_flexray_frame(spec.name, self.pkg['Frames'], FRAME_LENGTH)
            _describe(frame.element, f'Slot {spec.slot}, base cycle {spec.base_cycle}, cycle '
                      f'repetition {REPETITION}: {", ".join(spec.pdus)} at bytes 0, 8, 16; their '
                      f'update bits are bits 0..2 of byte {UPDATE_BIT_BYTE}.')
            for i, pdu_name in enumerate(spec.pdus):
                frame.map_pdu(self.pdus[pdu_name], 64 * i, ByteOrder.MostSignificantByteLast,
                              update_bit=8 * UPDATE_BIT_BYTE + i)
            triggering = channel.trigger_frame(
                frame, spec.slot, FlexrayCommunicationCycle.Repetition(spec.base_cycle,
                                                                       CYCLE_REPETITION))
            senders = {self.senders[p] for p in spec.pdus}
            if len(senders) != 1:
                raise ParamError(f'make_arxml: {spec.name} mixes PDUs of senders {senders}')
            for name, ecu in self.ecus.items():
                direction = (CommunicationDirection.Out if (name,) in senders
                             else CommunicationDirection.In)
                triggering.connect_to_ecu(ecu, direction)

    # --- Ethernet: the Socket Adaptor header IDs --------------------------------------------

    def ethernet(self) -> None:
        """One UDP socket connection gateway <-> stack carrying every PDU with its header ID."""
        cluster = self.system.create_ethernet_cluster('DriftEthernet', self.pkg['Topology'])
        _describe(cluster.element, 'The Ethernet gateway forwards each PDU between FlexRay and '
                  'UDP with an AUTOSAR Socket Adaptor header (header ID, length, payload); '
                  f'header ID = 0x{HEADER_ID_BASE:08X} + the DBC\'s CAN id. Addresses are '
                  'examples, ports as config/bridge.yaml udp.')
        channel = cluster.create_physical_channel('DriftEthernet_Channel')
        sockets = {}
        for name, (address, port) in ((STATE_SENDER, GATEWAY_UDP), (COMMAND_SENDER, STACK_UDP)):
            ecu = self.ecus[name]
            controller = ecu.create_ethernet_communication_controller(f'{name}_Ethernet')
            controller.connect_physical_channel(f'{name}_EthernetConnector', channel)
            endpoint = channel.create_network_endpoint(
                f'{name}_Endpoint',
                NetworkEndpointAddress.IPv4(address=address,
                                            address_source=IPv4AddressSource.Fixed), ecu=ecu)
            sockets[name] = channel.create_socket_address(
                f'{name}_Udp', endpoint, TpConfig.UdpTp(port_number=port),
                SocketAddressType.Unicast(ecu))
        bundle = channel.create_socket_connection_bundle('DriftSoAd', sockets[STATE_SENDER])
        connection = bundle.create_bundled_connection(sockets[COMMAND_SENDER])
        for message in self.db.messages:
            header_id = HEADER_ID_BASE + message.frame_id
            ident, triggering = connection.create_socket_connection_ipdu_identifier(
                self.pdus[message.name], header_id)
            ident.element.comment = f' {message.name}: header ID 0x{header_id:08X} '
            for name, ecu in self.ecus.items():
                triggering.create_pdu_port(ecu, CommunicationDirection.Out
                                           if name in message.senders
                                           else CommunicationDirection.In)


def frame_duration(settings) -> float:
    """Air time of a static frame with action point offset [s] (FlexRay Protocol Specification
    2.1 Rev. A, ch. 3.2: TSS, FSS, each byte as a 2-bit BSS + 8 bits over the 5-byte header,
    payload and 3-byte CRC, then the FES, plus the 11-bit channel idle delimiter)."""
    payload = 2 * settings.payload_length_static
    bits = (settings.transmission_start_sequence_duration + 1 + 10 * (5 + payload + 3) + 2
            + 11)
    return bits * settings.bit + settings.action_point_offset * settings.macrotick_duration


def _describe(element, text: str | None) -> None:
    """DESC (English) of an element: where a value comes from, what it means."""
    if text:
        desc = element.get_or_create_sub_element('DESC')
        l2 = desc.create_sub_element('L-2')
        l2.set_attribute('L', 'EN')
        l2.character_data = _one_line(text)


def _one_line(text: str) -> str:
    return ' '.join(str(text).split())


def _display(path) -> str:
    """A path relative to the checkout when inside it, so the output is the same everywhere."""
    try:
        return str(Path(path).resolve().relative_to(REPO))
    except ValueError:
        return str(path)


if __name__ == '__main__':
    sys.exit(main())
