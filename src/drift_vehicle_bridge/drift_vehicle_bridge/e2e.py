"""AUTOSAR E2E protection of a PDU and the receiver's check of it (E2E_PXXCheck + E2E_SMCheck).

autosar-e2e (module ``e2e``) computes and checks the CRC of each profile; this module adds what
it leaves out: each profile's header layout (which bits the header owns), a counter the caller
sets, the length and data ID fields, the named reason a PDU fails, and the receiver's counter
check and state machine. Layouts follow the AUTOSAR E2E Protocol Specification (PRS E2E):

- P01, P11: CRC8 (SAE J1850) byte at ``offset``, 4-bit counter 0..14 in the low nibble of the next
  byte; data ID mode ``nibble`` sends the low nibble of the data ID's high byte in its high nibble.
- P02: CRC8H2F byte 0, 4-bit counter 0..15 in the low nibble of byte 1; the CRC takes the entry
  of a 16-value data ID list that the counter selects.
- P04: 12 bytes big-endian: length 16 bit, counter 16 bit, data ID 32 bit, CRC32P4.
- P05: CRC16 (CCITT-FALSE) little-endian, counter 8 bit.
- P06: CRC16 big-endian, length 16 bit, counter 8 bit.
- P07: 20 bytes big-endian: CRC64, length 32 bit, counter 32 bit, data ID 32 bit.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from enum import Enum
from functools import partial

from e2e import p01, p02, p04, p05, p06, p07, p11

from drift_control.params import ParamError

PROFILES = ('P01', 'P02', 'P04', 'P05', 'P06', 'P07', 'P11')
DATA_ID_MODES = {'P01': ('both', 'alt', 'low', 'nibble'), 'P11': ('both', 'nibble')}
_P01_MODES = {'both': p01.E2E_P01_DATAID_BOTH, 'alt': p01.E2E_P01_DATAID_ALT,
              'low': p01.E2E_P01_DATAID_LOW, 'nibble': p01.E2E_P01_DATAID_NIBBLE}
_P11_MODES = {'both': p11.E2E_P11_DATAID_BOTH, 'nibble': p11.E2E_P11_DATAID_NIBBLE}
_MODULES = {'P01': p01, 'P04': p04, 'P05': p05, 'P06': p06, 'P07': p07, 'P11': p11}


@dataclass(frozen=True)
class _Layout:
    """Where a profile keeps its fields, in bytes from the header start."""

    size: int                 # header length [bytes]
    counter_modulo: int
    counter_at: int           # counter byte (a nibble for the 4-bit counters)
    counter_bytes: int        # 0: low nibble of one byte
    data_id_max: int          # largest data ID (0: the profile has a data ID list instead)
    length_field: tuple[int, int] | None = None     # (at, bytes), big-endian
    data_id_field: int | None = None                # at, 4 bytes big-endian


_LAYOUTS = {
    'P01': _Layout(2, 15, 1, 0, 0xFFFF),
    'P02': _Layout(2, 16, 1, 0, 0),
    'P04': _Layout(12, 1 << 16, 2, 2, 0xFFFFFFFF, length_field=(0, 2), data_id_field=4),
    'P05': _Layout(3, 1 << 8, 2, 1, 0xFFFF),
    'P06': _Layout(5, 1 << 8, 4, 1, 0xFFFF, length_field=(2, 2)),
    'P07': _Layout(20, 1 << 32, 12, 4, 0xFFFFFFFF, length_field=(8, 4), data_id_field=16),
    'P11': _Layout(2, 15, 1, 0, 0xFFFF),
}


@dataclass(frozen=True)
class E2EConfig:
    """One PDU's E2E protection as a description states it (its PDU length: ``protection``)."""

    profile: str                          # 'P01' 'P02' 'P04' 'P05' 'P06' 'P07' 'P11'
    data_id: int = 0                      # P01/P05/P06/P11: 16 bit; P04/P07: 32 bit; P02: unused
    data_id_list: tuple[int, ...] = ()    # P02: exactly 16 values 0..255
    offset: int = 0                       # byte offset of the E2E header in the PDU [bytes]
    data_id_mode: str = 'both'            # P01: both | alt | low | nibble; P11: both | nibble

    def __post_init__(self):
        where = f'e2e {self.profile}'
        if self.profile not in _LAYOUTS:
            raise ParamError(f'e2e: unknown profile {self.profile!r} (supported: {PROFILES})')
        modes = DATA_ID_MODES.get(self.profile, ('both',))
        if self.data_id_mode not in modes:
            raise ParamError(f'{where}: data_id_mode {self.data_id_mode!r} not one of {modes}')
        try:
            object.__setattr__(self, 'data_id_list', tuple(self.data_id_list))   # YAML: a list
        except TypeError:
            raise ParamError(f'{where}: data_id_list must be a sequence, '
                             f'got {self.data_id_list!r}') from None
        if self.profile == 'P02':
            if len(self.data_id_list) != 16 or not all(
                    isinstance(v, int) and 0 <= v <= 0xFF for v in self.data_id_list):
                raise ParamError(f'{where}: data_id_list must be 16 values 0..255, '
                                 f'got {self.data_id_list!r}')
            if self.offset != 0:
                raise ParamError(f'{where}: the header is bytes 0..1, offset must be 0')
        else:
            _check_data_id(where, self, self.data_id)
            if self.data_id_list:
                raise ParamError(f'{where}: data_id_list is for P02 only')
        if not isinstance(self.offset, int) or self.offset < 0:
            raise ParamError(f'{where}: offset must be a byte count >= 0, got {self.offset!r}')


def _check_data_id(where: str, cfg: E2EConfig, data_id) -> None:
    top = _LAYOUTS[cfg.profile].data_id_max
    if cfg.data_id_mode == 'nibble':
        top = 0x0FFF            # the high nibble of the high byte is neither sent nor in the CRC
    if not isinstance(data_id, int) or not 0 <= data_id <= top:
        raise ParamError(f'{where}: data_id {data_id!r} out of range 0..0x{top:X}')


def protection(cfg: E2EConfig, length: int) -> 'Protection':
    """The E2E protection of a ``length``-byte PDU; ParamError if the header does not fit."""
    return Protection(cfg, length)


class Protection:
    """Protect and verify one PDU layout: a config and its PDU length.

    Parameters
    ----------
    cfg : E2EConfig
        Profile, data ID(s), header offset.
    length : int
        PDU length [bytes]; P04's and P06's length fields carry it.
    """

    def __init__(self, cfg: E2EConfig, length: int):
        layout = _LAYOUTS[cfg.profile]
        where = f'e2e {cfg.profile}'
        if not isinstance(length, int) or cfg.offset + layout.size > length:
            raise ParamError(f'{where}: a {layout.size}-byte header at offset {cfg.offset} does '
                             f'not fit in a {length}-byte PDU')
        if layout.length_field and length >= 1 << (8 * layout.length_field[1]):
            raise ParamError(f'{where}: PDU length {length} does not fit the length field')
        self.config = cfg
        self.profile = cfg.profile
        self.length = length
        self.counter_modulo = layout.counter_modulo
        o = cfg.offset
        self._counter_at = o + layout.counter_at
        self._counter_end = self._counter_at + layout.counter_bytes   # == at for a nibble
        header = {8 * o + b for b in range(8 * layout.size)}
        if layout.size == 2 and cfg.data_id_mode != 'nibble':
            header -= {8 * (o + 1) + b for b in range(4, 8)}   # the counter byte's high nibble
        self.header_bits = frozenset(header)
        # Explicit header fields: (start, end, expected bytes, error name), checked before the CRC.
        self._fields = []
        if layout.length_field:
            at, size = layout.length_field
            self._fields.append((o + at, o + at + size, length.to_bytes(size, 'big'), 'length'))
        if layout.data_id_field is not None:
            at = o + layout.data_id_field
            self._fields.append((at, at + 4, cfg.data_id.to_bytes(4, 'big'), 'data_id'))
        self._nibble = (cfg.data_id >> 8) & 0x0F if cfg.data_id_mode == 'nibble' else None
        own = cfg.data_id_list if cfg.profile == 'P02' else cfg.data_id
        self._protect = self._library_call('protect', own)
        self._crc_ok = self._library_call('check', own)

    def _library_call(self, kind: str, data_id):
        """autosar-e2e's protect (counter left as written) or CRC check for ``data_id``."""
        cfg, n = self.config, self.length
        if cfg.profile == 'P02':
            fn = p02.e2e_p02_protect if kind == 'protect' else p02.e2e_p02_check
            extra = {'increment_counter': False} if kind == 'protect' else {}
            return partial(fn, data_id_list=bytes(data_id), length=n, **extra)
        module = _MODULES[cfg.profile]
        kwargs = {'length': n, 'offset': cfg.offset}
        if cfg.profile in ('P01', 'P11'):
            modes = _P01_MODES if cfg.profile == 'P01' else _P11_MODES
            kwargs['data_id_mode'] = modes[cfg.data_id_mode]
        if kind == 'protect':
            return partial(getattr(module, f'e2e_{cfg.profile.lower()}_protect'), data_id=data_id,
                           increment_counter=False, **kwargs)
        check = partial(getattr(module, f'e2e_{cfg.profile.lower()}_check'), data_id=data_id,
                        **kwargs)
        if cfg.profile in ('P01', 'P11'):
            # autosar-e2e 1.0 refuses read-only buffers here although it only reads them.
            return lambda data: check(bytearray(data))
        return check

    def protect(self, data: bytearray, counter: int) -> None:
        """Write the counter (mod ``counter_modulo``), length and data ID fields, then the CRC."""
        if len(data) != self.length:
            raise ValueError(f'e2e {self.profile}: {len(data)}-byte PDU, expected {self.length}')
        counter %= self.counter_modulo
        at, end = self._counter_at, self._counter_end
        if end == at:
            data[at] = (data[at] & 0xF0) | counter
        else:
            data[at:end] = counter.to_bytes(end - at, 'big')
        self._protect(data)

    def verify(self, data: bytes) -> str | None:
        """None if intact, else 'length', 'data_id' (a header field) or 'crc'."""
        if len(data) != self.length:
            return 'length'
        for start, end, expected, name in self._fields:
            if data[start:end] != expected:
                return name
        if self._nibble is not None and data[self._counter_at] >> 4 != self._nibble:
            return 'data_id'
        return None if self._crc_ok(data) else 'crc'

    def counter(self, data: bytes) -> int:
        """The counter a PDU carries (a P01/P11 value of 15 is invalid and fails ``verify``)."""
        at, end = self._counter_at, self._counter_end
        return data[at] & 0x0F if end == at else int.from_bytes(data[at:end], 'big')

    def crc_check_for(self, data_id):
        """A ``data -> bool`` CRC check with another PDU's data ID (P02: its data ID list)."""
        _check_other(self.config, data_id)
        return self._library_call('check', tuple(data_id) if self.profile == 'P02' else data_id)


def _check_other(cfg: E2EConfig, data_id) -> None:
    where = f'e2e {cfg.profile} other data ID'
    if cfg.profile == 'P02':
        if len(data_id) != 16 or not all(isinstance(v, int) and 0 <= v <= 0xFF for v in data_id):
            raise ParamError(f'{where}: a P02 data ID list must be 16 values 0..255')
    else:
        _check_data_id(where, cfg, data_id)


class ProfileStatus(str, Enum):
    """Result of one check (AUTOSAR E2E_PXXCheckStatusType, P04-style names)."""

    OK = 'OK'
    OK_SOME_LOST = 'OK_SOME_LOST'
    REPEATED = 'REPEATED'
    WRONG_SEQUENCE = 'WRONG_SEQUENCE'
    ERROR = 'ERROR'
    NO_NEW_DATA = 'NO_NEW_DATA'


class SMState(str, Enum):
    """AUTOSAR E2E_SMStateType."""

    NODATA = 'NODATA'
    INIT = 'INIT'
    VALID = 'VALID'
    INVALID = 'INVALID'


@dataclass(frozen=True)
class SMConfig:
    """AUTOSAR E2E_SMConfigType: counts of OK and ERROR checks within the last ``window_size``."""

    window_size: int = 3
    min_ok_state_init: int = 2
    max_error_state_init: int = 0
    min_ok_state_valid: int = 1
    max_error_state_valid: int = 0
    min_ok_state_invalid: int = 2
    max_error_state_invalid: int = 0

    def __post_init__(self):
        # The configuration constraints AUTOSAR implementations check in E2E_SMCheck.
        values = [getattr(self, f.name) for f in fields(self)]
        if not all(isinstance(v, int) and v >= 0 for v in values) or self.window_size < 1:
            raise ParamError(f'e2e state machine: counts must be integers >= 0 and window_size '
                             f'>= 1, got {self}')
        for state in ('init', 'valid', 'invalid'):
            ok = getattr(self, f'min_ok_state_{state}')
            err = getattr(self, f'max_error_state_{state}')
            if ok + err > self.window_size:
                raise ParamError(f'e2e state machine: min_ok_state_{state} ({ok}) + '
                                 f'max_error_state_{state} ({err}) exceed window_size '
                                 f'({self.window_size})')
        if not 1 <= self.min_ok_state_valid <= self.min_ok_state_init <= self.min_ok_state_invalid:
            raise ParamError('e2e state machine: need 1 <= min_ok_state_valid <= '
                             'min_ok_state_init <= min_ok_state_invalid')
        if not self.max_error_state_valid >= self.max_error_state_init \
                >= self.max_error_state_invalid:
            raise ParamError('e2e state machine: need max_error_state_valid >= '
                             'max_error_state_init >= max_error_state_invalid')


_OK = (ProfileStatus.OK, ProfileStatus.OK_SOME_LOST)


class Receiver:
    """One received PDU's E2E check (E2E_PXXCheck) and state machine (E2E_SMCheck).

    Parameters
    ----------
    protection : Protection
        The PDU's layout and data ID.
    max_delta_counter : int
        Largest counter step still accepted (as OK_SOME_LOST when > 1).
    sm : SMConfig
        State machine thresholds.
    other_data_ids : iterable
        Data IDs of the description's other PDUs (P02: their data ID lists). For profiles whose
        data ID is only inside the CRC, a PDU failing its own CRC but passing one of these is an
        ERROR named 'data_id' (misrouted or masquerading), not 'crc'.
    """

    def __init__(self, protection: Protection, max_delta_counter: int, sm: SMConfig,
                 other_data_ids=()):
        modulo = protection.counter_modulo
        if not isinstance(max_delta_counter, int) or not 1 <= max_delta_counter < modulo:
            raise ParamError(f'e2e {protection.profile}: max_delta_counter must be 1..'
                             f'{modulo - 1}, got {max_delta_counter!r}')
        self.protection = protection
        self.max_delta_counter = max_delta_counter
        self.sm = sm
        own = protection.config.data_id_list or protection.config.data_id
        explicit = protection.profile in ('P04', 'P07')     # the header carries the data ID
        self._others = [] if explicit else [
            protection.crc_check_for(i) for i in other_data_ids
            if (tuple(i) if protection.profile == 'P02' else i) != own]
        self.reset()

    def reset(self) -> None:
        """Back to the state after init: no counter known, state NODATA (E2E_SMCheckInit)."""
        self.status: ProfileStatus = ProfileStatus.NO_NEW_DATA
        self.rx_status: ProfileStatus | None = None
        self.error: str | None = None
        self.state = SMState.NODATA
        self._last: int | None = None
        self._window = [0] * self.sm.window_size      # 1 OK, -1 ERROR, 0 anything else
        self._top = 0
        self._ok = self._err = 0

    def check(self, data: bytes | None) -> ProfileStatus:
        """Check one received PDU; None when it did not arrive this cycle."""
        if data is None:
            status = ProfileStatus.NO_NEW_DATA
        else:
            error = self.protection.verify(data)
            if error == 'crc' and any(ok(data) for ok in self._others):
                error = 'data_id'
            if error:
                status = ProfileStatus.ERROR
            else:
                counter = self.protection.counter(data)
                status = ProfileStatus.OK if self._last is None else self._sequence(counter)
                self._last = counter      # a wrong sequence resynchronises on the new counter
            self.error = error
            self.rx_status = status
        self.status = status
        self._sm_check(status)
        return status

    def _sequence(self, counter: int) -> ProfileStatus:
        delta = (counter - self._last) % self.protection.counter_modulo
        if delta == 0:
            return ProfileStatus.REPEATED
        if delta == 1:
            return ProfileStatus.OK
        if delta <= self.max_delta_counter:
            return ProfileStatus.OK_SOME_LOST
        return ProfileStatus.WRONG_SEQUENCE

    def _sm_check(self, status: ProfileStatus) -> None:
        if self.state is SMState.NODATA:
            # The PDU that leaves NODATA is not counted: the window starts empty in INIT.
            if status is not ProfileStatus.ERROR and status is not ProfileStatus.NO_NEW_DATA:
                self.state = SMState.INIT
            return
        mark = 1 if status in _OK else -1 if status is ProfileStatus.ERROR else 0
        old = self._window[self._top]
        self._ok += (mark == 1) - (old == 1)
        self._err += (mark == -1) - (old == -1)
        self._window[self._top] = mark
        self._top = (self._top + 1) % len(self._window)
        ok, err, c = self._ok, self._err, self.sm
        if self.state is SMState.INIT:
            if err > c.max_error_state_init:
                self.state = SMState.INVALID
            elif ok >= c.min_ok_state_init:
                self.state = SMState.VALID
        elif self.state is SMState.VALID:
            if err > c.max_error_state_valid or ok < c.min_ok_state_valid:
                self.state = SMState.INVALID
        elif err <= c.max_error_state_invalid and ok >= c.min_ok_state_invalid:
            self.state = SMState.VALID

    @property
    def valid(self) -> bool:
        """The last received PDU may be used: state VALID and its check OK or OK_SOME_LOST."""
        return self.state is SMState.VALID and self.rx_status in _OK

    def reason(self) -> str:
        """Status and state for diagnostics, e.g. 'ERROR (crc), INVALID'."""
        status = self.status.value
        if self.status is ProfileStatus.ERROR:
            status += f' ({self.error})'
        return f'{status}, {self.state.value}'


__all__ = ['E2EConfig', 'PROFILES', 'Protection', 'ProfileStatus', 'Receiver', 'SMConfig',
           'SMState', 'protection']
