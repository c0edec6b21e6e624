"""TNO MF-Tyre property files (``.tir``): the reader and the steady-state Magic Formula forces.

``load_tir`` reads an MF 5.2 or MF 6.1/6.2 file into a frozen ``TirTyre``; ``mf_forces`` evaluates
its pure- and combined-slip forces ``Fx``, ``Fy`` at zero camber, zero turn slip and nominal
inflation pressure, vectorised with numpy. The controller never runs this model: it is the
reference ``drift_control.tyre_fit`` fits the controller's forms to.

Equations: H. B. Pacejka, *Tire and Vehicle Dynamics*, 3rd ed., Elsevier 2012, section 4.3.2
(Eqs. 4.E1-4.E67, the MF 6.1 set with the inflation-pressure terms of Besselink, Schmeitz and
Pacejka, VSD 48 suppl. 1, 2010). With camber, turn slip and pressure change all zero, MF 5.2 (as
in the PAC2002 files) differs from MF 6.1 only in the friction scale of the vertical shifts: MF
6.1 uses the digressive ``lambda'_mu`` of Eq. 4.E8, MF 5.2 ``lambda_mu`` itself. MF 6.2 changes
moments, radius and rolling resistance, not these forces, so it is evaluated as MF 6.1.

Sign convention as in the file (ISO W-axis): ``tan(alpha) = V_cy / |V_cx|``, so a normal tyre
gives ``Fy < 0`` for ``alpha > 0`` (its ``PKY1`` is negative); ``kappa > 0`` drives (``Fx > 0``).
"""
from __future__ import annotations

import math
import re
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path
from types import MappingProxyType
from typing import Mapping, NamedTuple

import numpy as np

from drift_control.params import ParamError

# FITTYP -> the equation set evaluated (TNO numbering: 6 and 21 are MF 5.2, 61/62 MF 6.1/6.2)
MF_VERSIONS = {6: '5.2', 21: '5.2', 61: '6.1', 62: '6.2'}
_NUMERIC_SECTIONS = ('DIMENSION', 'VERTICAL', 'SCALING_COEFFICIENTS',
                     'LONGITUDINAL_COEFFICIENTS', 'LATERAL_COEFFICIENTS')
_SI_UNITS = {'LENGTH': {'meter', 'metre', 'm'}, 'FORCE': {'newton', 'n'},
             'ANGLE': {'radian', 'radians', 'rad'}}
_A_MU = 10.0     # A_mu of Eq. 4.E8 (digressive friction scale of the vertical shifts)
_EPS = 1e-6      # the epsilon of Eqs. 4.E16, 4.E26: keeps B finite at zero load


@dataclass(frozen=True)
class Scaling:
    """User scaling factors lambda (``[SCALING_COEFFICIENTS]``); a missing one is 1."""

    LFZO: float = 1.0    # nominal load
    LCX: float = 1.0     # Fx shape factor
    LMUX: float = 1.0    # Fx peak friction
    LEX: float = 1.0     # Fx curvature
    LKX: float = 1.0     # Fx slip stiffness
    LHX: float = 1.0     # Fx horizontal shift
    LVX: float = 1.0     # Fx vertical shift
    LCY: float = 1.0     # Fy shape factor
    LMUY: float = 1.0    # Fy peak friction
    LEY: float = 1.0     # Fy curvature
    LKY: float = 1.0     # Fy cornering stiffness
    LHY: float = 1.0     # Fy horizontal shift
    LVY: float = 1.0     # Fy vertical shift
    LXAL: float = 1.0    # alpha influence on Fx (combined slip)
    LYKA: float = 1.0    # kappa influence on Fy (combined slip)
    LVYKA: float = 1.0   # kappa-induced side force


@dataclass(frozen=True)
class Longitudinal:
    """``[LONGITUDINAL_COEFFICIENTS]``: pure slip P*X*, combined slip R*X*; missing ones are 0.

    ``PCX1``, ``PDX1`` and ``PKX1`` are required (the formula divides by them).
    """

    PCX1: float
    PDX1: float
    PKX1: float
    PDX2: float = 0.0
    PDX3: float = 0.0
    PEX1: float = 0.0
    PEX2: float = 0.0
    PEX3: float = 0.0
    PEX4: float = 0.0
    PKX2: float = 0.0
    PKX3: float = 0.0
    PHX1: float = 0.0
    PHX2: float = 0.0
    PVX1: float = 0.0
    PVX2: float = 0.0
    PPX1: float = 0.0
    PPX2: float = 0.0
    PPX3: float = 0.0
    PPX4: float = 0.0
    RBX1: float = 0.0    # 0: no combined-slip reduction of Fx (G_xa = 1)
    RBX2: float = 0.0
    RBX3: float = 0.0
    RCX1: float = 0.0
    REX1: float = 0.0
    REX2: float = 0.0
    RHX1: float = 0.0


@dataclass(frozen=True)
class Lateral:
    """``[LATERAL_COEFFICIENTS]``: pure slip P*Y*, combined slip R*Y*; missing ones are 0.

    ``PCY1``, ``PDY1``, ``PKY1`` and ``PKY2`` are required. ``PKY4`` defaults to 2, the value MF
    5.2 has built in (``sin(2 atan(Fz / (PKY2 Fz0)))``), so an MF 5.2 file means the same in 6.1.
    """

    PCY1: float
    PDY1: float
    PKY1: float
    PKY2: float
    PDY2: float = 0.0
    PDY3: float = 0.0
    PEY1: float = 0.0
    PEY2: float = 0.0
    PEY3: float = 0.0
    PEY4: float = 0.0
    PEY5: float = 0.0
    PKY3: float = 0.0
    PKY4: float = 2.0
    PKY5: float = 0.0
    PKY6: float = 0.0
    PKY7: float = 0.0
    PHY1: float = 0.0
    PHY2: float = 0.0
    PHY3: float = 0.0
    PVY1: float = 0.0
    PVY2: float = 0.0
    PVY3: float = 0.0
    PVY4: float = 0.0
    PPY1: float = 0.0
    PPY2: float = 0.0
    PPY3: float = 0.0
    PPY4: float = 0.0
    PPY5: float = 0.0
    RBY1: float = 0.0    # 0: no combined-slip reduction of Fy (G_yk = 1)
    RBY2: float = 0.0
    RBY3: float = 0.0
    RBY4: float = 0.0
    RCY1: float = 0.0
    REY1: float = 0.0
    REY2: float = 0.0
    RHY1: float = 0.0
    RHY2: float = 0.0
    RVY1: float = 0.0
    RVY2: float = 0.0
    RVY3: float = 0.0
    RVY4: float = 0.0
    RVY5: float = 0.0
    RVY6: float = 0.0


@dataclass(frozen=True)
class TirTyre:
    """One tyre property file: the force coefficients, and every key of every section as read.

    Attributes
    ----------
    source : str
        The file it was read from.
    version : str
        Magic Formula version: ``'5.2'``, ``'6.1'`` or ``'6.2'``.
    FNOMIN : float
        Nominal wheel load ``Fz0`` [N] (before ``LFZO``).
    UNLOADED_RADIUS : float or None
        Free tyre radius ``R0`` [m], if the file gives it (not used by the forces).
    sections : mapping
        ``{section: {KEY: value}}``, upper-case names, numbers as float, strings unquoted.
    """

    source: str
    version: str
    FNOMIN: float
    UNLOADED_RADIUS: float | None
    scaling: Scaling
    longitudinal: Longitudinal
    lateral: Lateral
    sections: Mapping[str, Mapping[str, object]] = field(repr=False, compare=False)

    @property
    def Fz0(self) -> float:
        """Scaled nominal load ``Fz0' = LFZO * FNOMIN`` [N] (Eq. 4.E1)."""
        return self.scaling.LFZO * self.FNOMIN


class MfForces(NamedTuple):
    """Tyre forces in the tyre's own (ISO W-axis) frame [N]."""

    Fx: np.ndarray
    Fy: np.ndarray


# --- reading ----------------------------------------------------------------------------------

_SECTION = re.compile(r'^\[\s*([A-Za-z0-9_]+)\s*\]')


def parse_tir(text: str, source: str = '<tir>') -> dict[str, dict[str, object]]:
    """Sections of a ``.tir`` text: ``{SECTION: {KEY: float or str}}``.

    ``!`` and ``$`` start comments (whole lines, or after a value), ``'...'`` and ``"..."`` are
    strings; lines without ``=`` (the ``[SHAPE]`` table) are skipped. A repeated key is an error.
    """
    sections: dict[str, dict[str, object]] = {}
    current = sections.setdefault('', {})
    name = ''
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] in '!$':
            continue
        header = _SECTION.match(line)
        if header:
            name = header.group(1).upper()
            current = sections.setdefault(name, {})
            continue
        if '=' not in line:
            continue
        key, value = line.split('=', 1)
        key = key.strip().upper()
        if key in current:
            raise ParamError(f'{source}: [{name}] {key}: given twice (line {number})')
        current[key] = _value(value.strip())
    return sections


def _value(text: str):
    """A value without its trailing comment: a quoted string, a float, or the bare word."""
    if text[:1] in ('"', "'"):
        end = text.find(text[0], 1)
        return text[1:end] if end > 0 else text[1:]
    bare = re.split(r'[$!]', text, maxsplit=1)[0].strip()
    for candidate in (bare, bare.replace('D', 'E').replace('d', 'e')):   # Fortran 1.0D-3
        try:
            return float(candidate)
        except ValueError:
            pass
    return bare


def load_tir(path) -> TirTyre:
    """Read a TNO ``.tir`` tyre property file (MF 5.2, 6.1 or 6.2) into a ``TirTyre``.

    Raises
    ------
    ParamError
        One line naming the file and the key: file missing or unreadable, a required section
        (``[LONGITUDINAL_COEFFICIENTS]``, ``[LATERAL_COEFFICIENTS]``, ``[VERTICAL] FNOMIN``) or
        coefficient missing, a coefficient that is not a finite number, non-SI ``[UNITS]``, an
        unknown ``FITTYP``.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8', errors='replace')
    except FileNotFoundError:
        raise ParamError(f'{path}: tyre property file not found') from None
    except OSError as err:
        raise ParamError(f'{path}: cannot read: {err.strerror or err}') from None
    return tir_from_sections(parse_tir(text, str(path)), str(path))


def tir_from_sections(sections: dict[str, dict[str, object]], source: str) -> TirTyre:
    """Validate parsed sections and build the ``TirTyre`` (see ``load_tir``)."""
    for name in ('LONGITUDINAL_COEFFICIENTS', 'LATERAL_COEFFICIENTS', 'VERTICAL'):
        if name not in sections:
            raise ParamError(f'{source}: missing section [{name}]')
    for name in _NUMERIC_SECTIONS:
        for key, value in sections.get(name, {}).items():
            if not isinstance(value, float):
                raise ParamError(f'{source}: [{name}] {key}: expected a number, got {value!r}')
            if not math.isfinite(value):
                raise ParamError(f'{source}: [{name}] {key}: must be finite, got {value!r}')
    for key, allowed in _SI_UNITS.items():
        unit = sections.get('UNITS', {}).get(key)
        if unit is not None and str(unit).strip().lower() not in allowed:
            raise ParamError(f'{source}: [UNITS] {key}: only SI units are read, got {unit!r}')
    vertical = sections['VERTICAL']
    if 'FNOMIN' not in vertical:
        raise ParamError(f'{source}: [VERTICAL] FNOMIN: missing (the nominal load)')
    if not vertical['FNOMIN'] > 0:
        raise ParamError(f'{source}: [VERTICAL] FNOMIN: must be positive, '
                         f"got {vertical['FNOMIN']}")
    radius = sections.get('DIMENSION', {}).get('UNLOADED_RADIUS')
    frozen = MappingProxyType({k: MappingProxyType(dict(v)) for k, v in sections.items()})
    return TirTyre(
        source=source, version=_version(sections.get('MODEL', {}), source),
        FNOMIN=vertical['FNOMIN'], UNLOADED_RADIUS=radius,
        scaling=_coefficients(Scaling, sections.get('SCALING_COEFFICIENTS', {}),
                              'SCALING_COEFFICIENTS', source),
        longitudinal=_coefficients(Longitudinal, sections['LONGITUDINAL_COEFFICIENTS'],
                                   'LONGITUDINAL_COEFFICIENTS', source),
        lateral=_coefficients(Lateral, sections['LATERAL_COEFFICIENTS'],
                              'LATERAL_COEFFICIENTS', source),
        sections=frozen)


def _version(model: dict, source: str) -> str:
    fittyp = model.get('FITTYP')
    if fittyp is None:
        # PAC2002 files (MSC Adams) carry no FITTYP; their equations are MF 5.2
        if str(model.get('PROPERTY_FILE_FORMAT', '')).upper() == 'PAC2002':
            return '5.2'
        raise ParamError(f'{source}: [MODEL] FITTYP: missing (and PROPERTY_FILE_FORMAT is not '
                         "'PAC2002'): cannot tell the Magic Formula version")
    if not isinstance(fittyp, float) or fittyp not in MF_VERSIONS:
        known = ', '.join(f'{k} (MF {v})' for k, v in MF_VERSIONS.items())
        raise ParamError(f'{source}: [MODEL] FITTYP: unknown Magic Formula version {fittyp!r}; '
                         f'known: {known}')
    return MF_VERSIONS[int(fittyp)]


def _coefficients(cls, values: dict, section: str, source: str):
    """The dataclass ``cls`` from a section; required coefficients (no default) must be there."""
    names = {f.name for f in fields(cls)}
    for f in fields(cls):
        if f.name not in values and f.default is MISSING:
            raise ParamError(f'{source}: [{section}] {f.name}: missing (required)')
        if f.default is MISSING and values[f.name] == 0.0 or f.name == 'LFZO' \
                and values.get(f.name, 1.0) == 0.0:
            raise ParamError(f'{source}: [{section}] {f.name}: must not be 0 (the Magic Formula '
                             'divides by it)')
    return cls(**{k: v for k, v in values.items() if k in names})


# --- evaluation -------------------------------------------------------------------------------

def mf_forces(tyre: TirTyre, kappa, alpha, f_z, mu=1.0, alpha_star: bool = True) -> MfForces:
    """Steady-state combined-slip forces of the Magic Formula at zero camber [N].

    Pacejka (2012) Eqs. 4.E9-4.E30 (pure slip) and 4.E50-4.E67 (combined slip), with camber
    ``gamma = 0``, no turn slip (all ``zeta = 1``), nominal inflation pressure (``dp_i = 0``)
    and no slip-speed decay of friction (``LMUV`` not applied). Arrays broadcast.

    Parameters
    ----------
    tyre : TirTyre
        Coefficients.
    kappa : array_like
        Longitudinal slip [-]; positive drives.
    alpha : array_like
        Slip angle [rad], ISO sign (``tan(alpha) = V_cy / |V_cx|``); enters as ``tan(alpha)``.
    f_z : array_like
        Vertical load of the tyre [N], positive.
    mu : array_like
        Road friction scale [-]; multiplies ``LMUX`` and ``LMUY`` (it is ``lambda_mu``).
    alpha_star : bool
        True: the pure lateral force takes ``alpha* = tan(alpha)`` as the book writes (Eq.
        4.E20); False: ``alpha`` itself there, as some MF 6.1 implementations do (the
        teasit/magic-formula-tyre-library, for one). Combined slip uses ``tan(alpha)`` either way.
    """
    kappa, alpha, f_z, mu = np.broadcast_arrays(*(np.asarray(v, dtype=float)
                                                  for v in (kappa, alpha, f_z, mu)))
    s, lon, lat = tyre.scaling, tyre.longitudinal, tyre.lateral
    Fz0 = tyre.Fz0                                                     # 4.E1
    dfz = (f_z - Fz0) / Fz0                                            # 4.E2a
    alpha_s = np.tan(alpha)                                            # 4.E3, V_cx > 0
    lam_mux, lam_muy = s.LMUX * mu, s.LMUY * mu                        # 4.E7, LMUV = 0
    if tyre.version == '5.2':
        prime_x, prime_y = lam_mux, lam_muy
    else:
        prime_x, prime_y = _digressive(lam_mux), _digressive(lam_muy)  # 4.E8

    # longitudinal, pure slip (4.E9-4.E18)
    S_Hx = (lon.PHX1 + lon.PHX2 * dfz) * s.LHX
    kappa_x = kappa + S_Hx
    C_x = lon.PCX1 * s.LCX
    mu_x = (lon.PDX1 + lon.PDX2 * dfz) * lam_mux
    D_x = mu_x * f_z
    E_x = np.minimum((lon.PEX1 + lon.PEX2 * dfz + lon.PEX3 * dfz ** 2)
                     * (1.0 - lon.PEX4 * np.sign(kappa_x)) * s.LEX, 1.0)
    K_x = f_z * (lon.PKX1 + lon.PKX2 * dfz) * np.exp(lon.PKX3 * dfz) * s.LKX
    B_x = K_x / (C_x * D_x + _EPS)
    S_Vx = f_z * (lon.PVX1 + lon.PVX2 * dfz) * s.LVX * prime_x
    F_x0 = D_x * _shape(kappa_x, B_x, C_x, E_x) + S_Vx

    # lateral, pure slip (4.E19-4.E30)
    S_Hy = (lat.PHY1 + lat.PHY2 * dfz) * s.LHY
    alpha_y = (alpha_s if alpha_star else alpha) + S_Hy
    C_y = lat.PCY1 * s.LCY
    mu_y = (lat.PDY1 + lat.PDY2 * dfz) * lam_muy
    D_y = mu_y * f_z
    E_y = np.minimum((lat.PEY1 + lat.PEY2 * dfz) * (1.0 - lat.PEY3 * np.sign(alpha_y)) * s.LEY,
                     1.0)
    K_y = lat.PKY1 * Fz0 * np.sin(lat.PKY4 * np.arctan(f_z / (lat.PKY2 * Fz0))) * s.LKY
    B_y = K_y / (C_y * D_y + _EPS)
    S_Vy = f_z * (lat.PVY1 + lat.PVY2 * dfz) * s.LVY * prime_y
    F_y0 = D_y * _shape(alpha_y, B_y, C_y, E_y) + S_Vy

    # longitudinal, combined slip (4.E50-4.E57)
    B_xa = lon.RBX1 * np.cos(np.arctan(lon.RBX2 * kappa)) * s.LXAL
    E_xa = np.minimum(lon.REX1 + lon.REX2 * dfz, 1.0)
    S_Hxa = lon.RHX1
    G_xa = (_shape(alpha_s + S_Hxa, B_xa, lon.RCX1, E_xa, np.cos)
            / _shape(S_Hxa, B_xa, lon.RCX1, E_xa, np.cos))

    # lateral, combined slip (4.E58-4.E67)
    B_yk = lat.RBY1 * np.cos(np.arctan(lat.RBY2 * (alpha_s - lat.RBY3))) * s.LYKA
    E_yk = np.minimum(lat.REY1 + lat.REY2 * dfz, 1.0)
    S_Hyk = lat.RHY1 + lat.RHY2 * dfz
    G_yk = (_shape(kappa + S_Hyk, B_yk, lat.RCY1, E_yk, np.cos)
            / _shape(S_Hyk, B_yk, lat.RCY1, E_yk, np.cos))
    D_Vyk = mu_y * f_z * (lat.RVY1 + lat.RVY2 * dfz) * np.cos(np.arctan(lat.RVY4 * alpha_s))
    S_Vyk = D_Vyk * np.sin(lat.RVY5 * np.arctan(lat.RVY6 * kappa)) * s.LVYKA
    return MfForces(G_xa * F_x0, G_yk * F_y0 + S_Vyk)


def _shape(x, B, C, E, outer=np.sin):
    """``outer(C atan(B x - E (B x - atan(B x))))``: the Magic Formula and its cosine weight."""
    Bx = B * x
    return outer(C * np.arctan(Bx - E * (Bx - np.arctan(Bx))))


def _digressive(lam):
    """``lambda'_mu = A_mu lambda / (1 + (A_mu - 1) lambda)`` (Eq. 4.E8)."""
    return _A_MU * lam / (1.0 + (_A_MU - 1.0) * lam)
