"""FlexRay ARXML bus descriptions: the PDUs of a FLEXRAY-CLUSTER as a ``Description``.

autosar-data reads the file; nothing about the layout is assumed here. Each I-SIGNAL-I-PDU in a
frame of the cluster becomes a ``PduSpec``: a cantools message built from its signal mappings,
COMPU-METHODs, units and DATA-CONSTRs, the E2E configuration of its E2E transformer, its Socket
Adaptor header ID (SOCKET-CONNECTION-IPDU-IDENTIFIER) as the transport id, the senders from the
frame ports, the FlexRay schedule in ``bus``. ``scripts/make_arxml.py`` writes the shipped file.
"""
from __future__ import annotations

import os

import autosar_data
from autosar_data.abstraction import AutosarModelAbstraction, ByteOrder
from autosar_data.abstraction.communication import (
    CommunicationDirection, EndToEndTransformationISignalProps, EthernetCluster, FlexrayCluster,
    FlexrayCommunicationCycle, ISignalGroup, ISignalIPdu, ISignalToIPduMapping)
from autosar_data.abstraction.datatype import BaseTypeEncoding, DataConstrType
from cantools.database.can import Message, Signal
from cantools.database.conversion import BaseConversion

from drift_control.params import ParamError
from drift_vehicle_bridge.description import COMMAND_SIGNALS, STATE_SIGNALS, Description, PduSpec
from drift_vehicle_bridge.e2e import PROFILES, E2EConfig, protection

# autosar-data's DataIdMode (by name: its enum values are not hashable) -> E2EConfig's.
DATA_ID_MODES = {'All16Bit': 'both', 'Alternating8Bit': 'alt', 'Lower8Bit': 'low',
                 'Lower12Bit': 'nibble'}


def load_arxml(path: str | os.PathLike) -> Description:
    """Read the FlexRay PDUs of an ARXML file.

    Parameters
    ----------
    path : str or os.PathLike
        AUTOSAR 4 ARXML with a SYSTEM, a FLEXRAY-CLUSTER and the PDUs' Socket Adaptor header IDs.

    Returns
    -------
    Description
        ``kind`` 'flexray'; one ``PduSpec`` per I-SIGNAL-I-PDU in the cluster's frames (channel
        A, else B), in schedule order.

    Raises
    ------
    ParamError
        One line naming the file and what is wrong: unreadable or malformed XML, no FlexRay
        cluster, a PDU without header ID or E2E protection, an unsupported E2E profile or
        COMPU-METHOD, a missing state signal or command PDU signal.
    """
    try:
        specs = _Reader(path, AutosarModelAbstraction.from_file(str(path))).specs()
    except Exception as err:
        if not _is_autosar_error(err):
            raise
        raise ParamError(f'{path}: cannot read the ARXML: {_one_line(err)}') from None
    description = Description(str(path), 'flexray', tuple(specs))
    _check_contract(path, description)
    return description


class _Reader:
    """Walks one model: FlexRay cluster -> frames -> PDUs -> signals."""

    def __init__(self, path, model: AutosarModelAbstraction):
        self.path, self.model = path, model      # the model must outlive every reference read
        system = model.find_system()
        if system is None:
            raise ParamError(f'{path}: no SYSTEM')
        clusters = list(system.clusters())
        flexray = [c for c in clusters if isinstance(c, FlexrayCluster)]
        if not flexray:
            raise ParamError(f'{path}: no FLEXRAY-CLUSTER in system {system.name}')
        self.cluster = flexray[0]
        channels = self.cluster.physical_channels
        self.channel, self.channel_name = ((channels.channel_a, 'A') if channels.channel_a
                                           else (channels.channel_b, 'B'))
        if self.channel is None:
            raise ParamError(f'{path}: FlexRay cluster {self.cluster.name} has no channel')
        settings = self.cluster.settings()
        if settings is None or not settings.cycle > 0:
            raise ParamError(f'{path}: FlexRay cluster {self.cluster.name} has no cycle time')
        self.settings = settings
        self.header_ids = _header_ids(path, [c for c in clusters
                                             if isinstance(c, EthernetCluster)])

    def specs(self) -> list[PduSpec]:
        specs, seen = [], set()
        for triggering in self.channel.frame_triggerings():
            frame = triggering.frame
            ports = list(triggering.frame_ports())
            senders = tuple(p.ecu.name for p in ports
                            if p.communication_direction == CommunicationDirection.Out)
            receivers = [p.ecu.name for p in ports
                         if p.communication_direction == CommunicationDirection.In]
            cycle, base_cycle, repetition = self._timing(triggering)
            for mapping in frame.mapped_pdus():
                pdu = mapping.pdu
                if not isinstance(pdu, ISignalIPdu) or pdu.name in seen:
                    continue                      # not an I-SIGNAL-I-PDU, or scheduled twice
                seen.add(pdu.name)
                bus = {'cluster': self.cluster.name, 'channel': self.channel_name,
                       'slot': triggering.slot, 'base_cycle': base_cycle,
                       'repetition': repetition, 'frame': frame.name,
                       'offset': mapping.start_position // 8, 'update_bit': mapping.update_bit}
                specs.append(self._spec(pdu, senders, receivers, cycle, bus))
        if not specs:
            raise ParamError(f'{self.path}: FlexRay cluster {self.cluster.name} carries no '
                             f'I-SIGNAL-I-PDU')
        return specs

    def _timing(self, triggering) -> tuple[float, int, int]:
        """(period [s], base cycle, cycle repetition) of a frame triggering."""
        timing = triggering.timing()
        if isinstance(timing, FlexrayCommunicationCycle.Repetition):
            repetition = int(_name(timing.cycle_repetition)[1:])     # C2 -> 2
            return repetition * self.settings.cycle, timing.base_cycle, repetition
        if isinstance(timing, FlexrayCommunicationCycle.Counter):
            repetition = self.settings.cycle_count_max + 1
            return repetition * self.settings.cycle, timing.cycle_counter, repetition
        raise ParamError(f'{self.path}: frame {triggering.name} has no FlexRay timing')

    def _spec(self, pdu: ISignalIPdu, senders, receivers, cycle: float, bus: dict) -> PduSpec:
        where = f'{self.path}: {pdu.name}'
        if pdu.name not in self.header_ids:
            raise ParamError(f'{where}: no Socket Adaptor header ID (SOCKET-CONNECTION-IPDU-'
                             f'IDENTIFIER)')
        signals, e2e = [], None
        for element in _sub_elements(pdu.element, 'I-SIGNAL-TO-PDU-MAPPINGS'):
            mapping = ISignalToIPduMapping(element)
            if mapping.signal is not None:
                signals.append(self._signal(where, mapping, receivers))
            elif mapping.signal_group is not None and e2e is None:
                e2e = self._e2e(where, mapping.signal_group, pdu.length)
        if e2e is None:
            raise ParamError(f'{where}: no E2E protection (an I-SIGNAL-GROUP with an E2E '
                             f'transformer)')
        header_id = self.header_ids[pdu.name]
        try:
            # No CAN frame: frame_id 0 (cantools allows at most 29 bits there); cantools keeps
            # an AUTOSAR PDU header ID (of contained PDUs) in header_id.
            message = Message(0, pdu.name, pdu.length, signals, header_id=header_id,
                              comment=_desc(pdu.element), senders=list(senders),
                              cycle_time=round(1000 * cycle))
        except Exception as err:                  # noqa: BLE001 - cantools: overlapping signals
            raise ParamError(f'{where}: {_one_line(err)}') from None
        return PduSpec(name=pdu.name, id=header_id, length=pdu.length, message=message, e2e=e2e,
                       senders=senders, cycle=cycle, fd=None, bus=bus)

    def _signal(self, where: str, mapping, receivers) -> Signal:
        """A cantools signal from an I-SIGNAL-TO-I-PDU-MAPPING and what its signals refer to."""
        isignal = mapping.signal
        where = f'{where}.{isignal.name}'
        length, start = isignal.length, mapping.start_position
        if length is None or start is None:
            raise ParamError(f'{where}: no LENGTH or START-POSITION')
        byte_order = ('big_endian' if mapping.byte_order == ByteOrder.MostSignificantByteFirst
                      else 'little_endian')
        datatype = isignal.datatype
        signed = datatype is not None and (datatype.base_type_encoding
                                           == BaseTypeEncoding.TwosComplement)
        system_signal = isignal.system_signal
        scale, offset, choices = self._conversion(where, system_signal)
        unit = system_signal.unit if system_signal is not None else None
        minimum, maximum = self._limits(system_signal, scale, offset)
        return Signal(
            name=isignal.name, start=dbc_start(start, length, byte_order), length=length,
            byte_order=byte_order, is_signed=signed,
            conversion=BaseConversion.factory(scale=scale, offset=offset, choices=choices),
            minimum=minimum, maximum=maximum,
            unit=(unit.display_name or unit.name) if unit is not None else None,
            comment=_desc(isignal.element), receivers=list(receivers))

    @staticmethod
    def _conversion(where: str, system_signal):
        """(scale, offset, choices) of the system signal's COMPU-METHOD (identity if none)."""
        method = system_signal.compu_method if system_signal is not None else None
        content = method.content() if method is not None else None
        kind = type(content).__name__.rsplit('_', 1)[-1]
        if content is None or kind == 'Identical':
            return 1, 0, None
        if kind == 'Linear':
            return content.factor / content.divisor, content.offset / content.divisor, None
        if kind == 'TextTable':
            return 1, 0, {int(e.value): e.text for e in content.texts}
        raise ParamError(f'{where}: COMPU-METHOD {method.name} of category {kind} is not '
                         f'supported (IDENTICAL, LINEAR, TEXTTABLE)')

    @staticmethod
    def _limits(system_signal, scale, offset):
        """Physical [min, max] from the DATA-CONSTR (internal limits scaled)."""
        constr = system_signal.data_constr if system_signal is not None else None
        for rule in (constr.data_constr_rules() if constr is not None else ()):
            lo, hi = rule.lower_limit, rule.upper_limit
            if lo is None or hi is None:
                continue
            if rule.rule_type == DataConstrType.Internal:
                lo, hi = sorted((lo * scale + offset, hi * scale + offset))
            return _number(lo), _number(hi)
        return None, None

    def _e2e(self, where: str, group: ISignalGroup, length: int) -> E2EConfig | None:
        """The E2EConfig of the group's E2E transformer and its I-SIGNAL-PROPS (data IDs)."""
        for transformation in group.data_transformations():
            for technology in transformation.transformation_technologies():
                if technology.protocol != 'E2E':
                    continue                      # SOME/IP or another transformer in the chain
                config = technology.config()
                if type(config).__name__ != 'E2ETransformationTechnologyConfig':
                    raise ParamError(f'{where}: E2E transformer {technology.name} has no '
                                     f'profile autosar-data knows (PROFILE-NAME)')
                profile = _name(config.profile)
                if profile not in PROFILES:
                    raise ParamError(f'{where}: E2E profile {profile} is not supported '
                                     f'({", ".join(PROFILES)})')
                if config.offset % 8:
                    raise ParamError(f'{where}: E2E offset {config.offset} bits is not whole '
                                     f'bytes')
                data_ids = _data_ids(group, technology)
                if profile != 'P02' and len(data_ids) != 1:
                    raise ParamError(f'{where}: E2E {profile} needs one DATA-ID, found '
                                     f'{len(data_ids)}')
                try:
                    if profile == 'P02':
                        cfg = E2EConfig(profile, data_id_list=tuple(data_ids),
                                        offset=config.offset // 8)
                    else:
                        cfg = E2EConfig(profile, data_id=data_ids[0], offset=config.offset // 8,
                                        data_id_mode=DATA_ID_MODES.get(_name(config.data_id_mode),
                                                                       'both'))
                    protection(cfg, length)       # the header fits, the IDs are in range
                except ParamError as err:
                    raise ParamError(f'{where}: {err}') from None
                return cfg
        return None


def _data_ids(group: ISignalGroup, technology) -> list[int]:
    """DATA-IDS of the group's END-TO-END-TRANSFORMATION-I-SIGNAL-PROPS for ``technology``."""
    for props in group.transformation_isignal_props():
        if isinstance(props, EndToEndTransformationISignalProps) and (
                props.transformer is None or props.transformer == technology):
            return list(props.data_ids)
    return []


def _header_ids(path, clusters) -> dict[str, int]:
    """PDU name -> Socket Adaptor header ID from the socket connections of Ethernet clusters."""
    ids: dict[str, int] = {}
    for cluster in clusters:
        for channel in cluster.physical_channels():
            for bundle in channel.socket_connection_bundles():
                for connection in bundle.bundled_connections():
                    for ident in connection.socket_connection_ipdu_identifiers():
                        triggering = ident.pdu_triggering
                        pdu = triggering.pdu if triggering is not None else None
                        if pdu is None or ident.header_id is None:
                            continue
                        if ids.setdefault(pdu.name, ident.header_id) != ident.header_id:
                            raise ParamError(f'{path}: {pdu.name} has two header IDs '
                                             f'0x{ids[pdu.name]:08x}, 0x{ident.header_id:08x}')
    return ids


def _check_contract(path, description) -> None:
    """Every state signal in a PDU and each command PDU with its signals, as the codec needs."""
    carried = {s.name for spec in description.pdus for s in spec.message.signals}
    missing = sorted(set(STATE_SIGNALS) - carried)
    if missing:
        raise ParamError(f'{path}: no PDU carries the state signal(s) {missing}')
    pdus = {spec.name: spec for spec in description.pdus}
    for name, needed in COMMAND_SIGNALS.items():
        if name not in pdus:
            raise ParamError(f'{path}: no command PDU {name}')
        lacking = sorted(set(needed) - {s.name for s in pdus[name].message.signals})
        if lacking:
            raise ParamError(f'{path}: {name} lacks signal(s) {lacking}')


def dbc_start(position: int, length: int, byte_order: str) -> int:
    """cantools/DBC start bit of a signal whose AUTOSAR START-POSITION is ``position``.

    AUTOSAR counts the position of the least significant bit for both byte orders (bit 0 = LSB
    of byte 0); a DBC's big-endian start bit is the most significant bit in sawtooth numbering.
    """
    if byte_order == 'little_endian':
        return position
    for _ in range(length - 1):                   # LSB -> MSB: up within a byte, then a byte back
        position = position + 1 if position % 8 != 7 else position - 15
    return position


def autosar_start(start: int, length: int, byte_order: str) -> int:
    """AUTOSAR START-POSITION (the LSB) of a cantools signal; inverse of :func:`dbc_start`."""
    if byte_order == 'little_endian':
        return start
    for _ in range(length - 1):                   # MSB -> LSB: down within a byte, then forward
        start = start - 1 if start % 8 != 0 else start + 15
    return start


def _sub_elements(element, name: str) -> list:
    sub = element.get_sub_element(name)
    return list(sub.sub_elements) if sub is not None else []


def _desc(element) -> str | None:
    """The English (or first) DESC text of an element."""
    desc = element.get_sub_element('DESC')
    if desc is None:
        return None
    texts = {l2.attribute_value('L'): l2.character_data for l2 in desc.sub_elements}
    text = texts.get('EN', next(iter(texts.values()), None))
    return str(text) if text is not None else None


def _name(value) -> str:
    """The member name of an autosar-data enum value ('P02' for E2EProfile.P02)."""
    return str(value).rsplit('.', 1)[-1]


def _number(value: float):
    """An int where the value is whole, as cantools reads a DBC's limits."""
    return int(value) if float(value).is_integer() else value


def _is_autosar_error(err: Exception) -> bool:
    """Whether autosar-data raised ``err`` (0.17 raises ``AutosarAbstractionError``, a class it
    does not export, for unreadable files and malformed XML)."""
    return (isinstance(err, autosar_data.AutosarDataError)
            or type(err).__name__ == 'AutosarAbstractionError')


def _one_line(err) -> str:
    return ' '.join(str(err).split())


__all__ = ['autosar_start', 'dbc_start', 'load_arxml']
