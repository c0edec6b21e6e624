"""TNO .tir tyre files: reading (values, defaults, errors) and the Magic Formula forces."""
import dataclasses

import numpy as np
import pytest

from conftest import REPO
from drift_control.params import ParamError
from drift_control.tir import load_tir, mf_forces, parse_tir

SHIPPED = 'pacejka_book_205_60r15.tir'

MF52 = """\
$---------------------------------------------------------------- a PAC2002-style file
! comment lines start with ! or $
[MODEL]
PROPERTY_FILE_FORMAT     ='PAC2002'
TYRESIDE                 = 'LEFT'               $Mounted side
[UNITS]
LENGTH                   ='meter'
FORCE                    ='newton'
ANGLE                    ='radian'
[DIMENSION]
UNLOADED_RADIUS          = 0.344                $Free tyre radius
[SHAPE]
{radial width}
 1.0    0.0
 0.9    1.0
[VERTICAL]
FNOMIN                   = 4850                 $Nominal wheel load
[SCALING_COEFFICIENTS]
LFZO                     = 0.81
LMUY                     = 0.9
[LONGITUDINAL_COEFFICIENTS]
PCX1                     = 1.6411               $Shape factor Cfx
PDX1                     = 1.1739
PDX2                     = -0.16395
PEX1                     = 0.46403
PKX1                     = 22.303
PVX1                     = -8.8098D-006         $Fortran exponent
[LATERAL_COEFFICIENTS]
PCY1                     = 1.3507
PDY1                     = 1.0489
PDY2                     = -0.18033
PEY1                     = -0.0074722
PKY1                     = -21.92
PKY2                     = 2.0012
"""

MF61 = """\
[MDI_HEADER]
FILE_TYPE = 'tir'
[MODEL]
FITTYP = 61                 $Magic Formula version number
[VERTICAL]
FNOMIN = 4000
[LONGITUDINAL_COEFFICIENTS]
PCX1 = 1.6
PDX1 = 1.2
PKX1 = 20.0
RBX1 = 12.0
RCX1 = 1.0
[LATERAL_COEFFICIENTS]
PCY1 = 1.3
PDY1 = 1.0
PKY1 = -15.0
PKY2 = 2.0
PKY4 = 1.9
RBY1 = 7.0
RCY1 = 1.0
"""


def write(tmp_path, text, name='t.tir'):
    path = tmp_path / name
    path.write_text(text)
    return path


@pytest.fixture(scope='module')
def shipped():
    return load_tir(REPO / 'config' / 'tyres' / SHIPPED)


@pytest.fixture
def no_offsets(shipped):
    """The shipped tyre with every shift and asymmetry term set to zero."""
    lon = dataclasses.replace(shipped.longitudinal, PHX1=0.0, PHX2=0.0, PVX1=0.0, PVX2=0.0,
                              PEX4=0.0, RHX1=0.0)
    lat = dataclasses.replace(shipped.lateral, PHY1=0.0, PHY2=0.0, PVY1=0.0, PVY2=0.0,
                              PEY3=0.0, RBY3=0.0, RHY1=0.0, RHY2=0.0, RVY1=0.0, RVY2=0.0)
    return dataclasses.replace(shipped, longitudinal=lon, lateral=lat)


# --- reading ----------------------------------------------------------------------------------

def test_mf52_file_values_and_defaults(tmp_path):
    t = load_tir(write(tmp_path, MF52))
    assert t.version == '5.2'
    assert t.FNOMIN == 4850.0 and t.UNLOADED_RADIUS == 0.344
    assert t.Fz0 == pytest.approx(0.81 * 4850.0)
    assert t.longitudinal.PCX1 == 1.6411 and t.longitudinal.PDX2 == -0.16395
    assert t.longitudinal.PVX1 == pytest.approx(-8.8098e-6)
    assert t.lateral.PKY1 == -21.92
    # scaling factors default to 1, missing coefficients to 0, PKY4 to MF 5.2's built-in 2
    assert t.scaling.LMUY == 0.9 and t.scaling.LMUX == 1.0 and t.scaling.LKY == 1.0
    assert t.longitudinal.RBX1 == 0.0 and t.lateral.PHY1 == 0.0
    assert t.lateral.PKY4 == 2.0
    # every key is kept as read, strings unquoted
    assert t.sections['MODEL']['TYRESIDE'] == 'LEFT'
    assert t.sections['UNITS']['LENGTH'] == 'meter'


def test_mf61_file(tmp_path):
    t = load_tir(write(tmp_path, MF61))
    assert t.version == '6.1'
    assert t.lateral.PKY4 == 1.9 and t.longitudinal.RBX1 == 12.0
    assert t.UNLOADED_RADIUS is None


def test_shipped_file_is_the_published_set(shipped):
    assert shipped.version == '6.1' and shipped.FNOMIN == 4000.0
    assert shipped.lateral.PKY1 == -14.95 and shipped.lateral.PDY1 == -0.990
    assert shipped.longitudinal.RBX1 == 12.35 and shipped.lateral.RVY6 == -10.71


def test_comments_and_quotes_are_stripped():
    sections = parse_tir("[A]\nX = 1.5 $ c\nY = 'a $ b' ! c\nZ = word ! c\n")
    assert sections['A'] == {'X': 1.5, 'Y': 'a $ b', 'Z': 'word'}


def one_line_error(tmp_path, text, *fragments):
    path = write(tmp_path, text)
    with pytest.raises(ParamError) as err:
        load_tir(path)
    message = str(err.value)
    assert '\n' not in message and str(path) in message, message
    for fragment in fragments:
        assert fragment in message, message


@pytest.mark.parametrize('section', ['LONGITUDINAL_COEFFICIENTS', 'LATERAL_COEFFICIENTS',
                                     'VERTICAL'])
def test_missing_section(tmp_path, section):
    text = MF61.replace(f'[{section}]', '[SOMETHING_ELSE]')
    one_line_error(tmp_path, text, f'[{section}]')


def test_missing_fnomin(tmp_path):
    one_line_error(tmp_path, MF61.replace('FNOMIN = 4000', ''), 'FNOMIN')


def test_missing_required_coefficient(tmp_path):
    one_line_error(tmp_path, MF61.replace('PKY2 = 2.0', ''), 'PKY2')


@pytest.mark.parametrize('bad', ['abc', "'1.2'", '1.2.3'])
def test_non_numeric_coefficient_names_the_key(tmp_path, bad):
    one_line_error(tmp_path, MF61.replace('PDY1 = 1.0', f'PDY1 = {bad}'),
                   '[LATERAL_COEFFICIENTS] PDY1', 'number')


@pytest.mark.parametrize('fittyp', ['7', "'MF'"])
def test_unknown_fittyp(tmp_path, fittyp):
    one_line_error(tmp_path, MF61.replace('FITTYP = 61', f'FITTYP = {fittyp}'), 'FITTYP')


def test_other_errors(tmp_path):
    one_line_error(tmp_path, MF61.replace('FITTYP = 61', ''), 'FITTYP')
    one_line_error(tmp_path, MF61 + 'PKY1 = 1\n', 'PKY1', 'twice')
    one_line_error(tmp_path, MF52.replace("LENGTH                   ='meter'", "LENGTH='mm'"),
                   'LENGTH')
    with pytest.raises(ParamError, match='not found'):
        load_tir(tmp_path / 'nope.tir')


# --- the forces -------------------------------------------------------------------------------

def test_zero_slip_gives_the_shifts(shipped):
    """At zero slip only the shifts act: F ~ K S_H + S_V (B S_H << 1)."""
    f = mf_forces(shipped, 0.0, 0.0, 4000.0)       # Fz = Fz0: dfz = 0
    lon, lat = shipped.longitudinal, shipped.lateral
    K_x = lon.PKX1 * 4000.0
    K_y = lat.PKY1 * 4000.0 * np.sin(2.0 * np.arctan(1.0 / lat.PKY2))
    assert f.Fx == pytest.approx(K_x * lon.PHX1 + 4000.0 * lon.PVX1, rel=1e-3)
    assert f.Fy == pytest.approx(K_y * lat.PHY1 + 4000.0 * lat.PVY1, rel=2e-2)


def test_odd_without_offsets(no_offsets):
    alpha = np.radians([1.0, 5.0, 12.0, 30.0])
    for kappa in (0.0, 0.1):
        fy = mf_forces(no_offsets, kappa, alpha, 3500.0).Fy
        assert mf_forces(no_offsets, kappa, -alpha, 3500.0).Fy == pytest.approx(-fy, abs=1e-9)
    kappa = np.array([0.01, 0.1, 0.5])
    for a in (0.0, 0.2):
        fx = mf_forces(no_offsets, kappa, a, 3500.0).Fx
        assert mf_forces(no_offsets, -kappa, a, 3500.0).Fx == pytest.approx(-fx, abs=1e-9)
        assert mf_forces(no_offsets, kappa, -a, 3500.0).Fx == pytest.approx(fx, abs=1e-9)
    assert mf_forces(no_offsets, 0.0, 0.0, 3500.0) == (0.0, 0.0)


@pytest.mark.parametrize('mu', [1.0, 0.6])
@pytest.mark.parametrize('f_z', [2000.0, 4000.0, 6000.0])
def test_peak_is_mu_D_Fz(no_offsets, mu, f_z):
    lon, lat = no_offsets.longitudinal, no_offsets.lateral
    dfz = (f_z - 4000.0) / 4000.0
    kappa = np.linspace(0.0, 1.0, 4001)
    alpha = np.linspace(0.0, np.radians(60.0), 4001)
    peak_x = np.max(mf_forces(no_offsets, kappa, 0.0, f_z, mu).Fx)
    peak_y = np.max(np.abs(mf_forces(no_offsets, 0.0, alpha, f_z, mu).Fy))
    assert peak_x == pytest.approx(mu * (lon.PDX1 + lon.PDX2 * dfz) * f_z, rel=1e-4)
    assert peak_y == pytest.approx(mu * abs(lat.PDY1 + lat.PDY2 * dfz) * f_z, rel=1e-4)


def test_cornering_stiffness_does_not_scale_with_mu(no_offsets):
    """lambda_mu lowers the peak but not K_y: B_y = K_y / (C_y D_y) grows as mu falls."""
    a = 1e-5
    k_dry = mf_forces(no_offsets, 0.0, a, 4000.0, 1.0).Fy / a
    k_wet = mf_forces(no_offsets, 0.0, a, 4000.0, 0.6).Fy / a
    assert k_wet == pytest.approx(k_dry, rel=1e-6)


def test_combined_slip_reduces_both_forces(shipped):
    alpha = np.radians([3.0, 8.0, 20.0, 35.0])
    pure_y = np.abs(mf_forces(shipped, 0.0, alpha, 4000.0).Fy)
    pure_x = mf_forces(shipped, 0.3, 0.0, 4000.0).Fx
    for kappa in (0.1, 0.3, 0.6):
        assert np.all(np.abs(mf_forces(shipped, kappa, alpha, 4000.0).Fy) < pure_y)
    assert np.all(mf_forces(shipped, 0.3, alpha, 4000.0).Fx < pure_x)
    # the friction circle: combined forces stay within the pure peaks
    f = mf_forces(shipped, 0.3, alpha, 4000.0)
    assert np.all(np.hypot(f.Fx / 4840.0, f.Fy / 4140.0) < 1.05)


def test_mf52_vertical_shift_scales_with_lambda_mu(tmp_path):
    """MF 5.2 scales S_V with lambda_mu itself, MF 6.1 with the digressive lambda'_mu."""
    text = MF61.replace('PCY1 = 1.3', 'PCY1 = 1.3\nPVY1 = 0.05')
    t61 = load_tir(write(tmp_path, text))
    t52 = load_tir(write(tmp_path, text.replace('FITTYP = 61', 'FITTYP = 21'), 'b.tir'))
    assert mf_forces(t52, 0.0, 0.0, 4000.0, 0.5).Fy == pytest.approx(0.5 * 0.05 * 4000.0)
    assert mf_forces(t61, 0.0, 0.0, 4000.0, 0.5).Fy == pytest.approx(10 * 0.5 / 5.5 * 200.0)
    assert mf_forces(t61, 0.0, 0.0, 4000.0, 1.0).Fy == pytest.approx(200.0)


# Forces of the shipped tyre computed by an independent MF 6.1 implementation (the
# teasit/magic-formula-tyre-library, as published in the golden CSVs of github.com/KMoula30/outlap,
# crates/outlap-tire/tests/golden/pacejka_2006_205_60r15/, for the same Table A3.1 coefficients).
# That implementation takes alpha, not tan(alpha), in the pure lateral force (alpha_star=False).
# Columns: kappa, alpha [rad], Fz [N], Fx [N], Fy [N].
GOLDEN = [
    (-0.25, -0.17, 4000.0, -3563.509474, 2203.153893),
    (-0.2, 0.102, 4000.0, -3996.39872, -2095.6568),
    (-0.05, -0.136, 4000.0, -1797.800527, 3752.806062),
    (0.05, -0.068, 4000.0, 2717.691781, 2671.528868),
    (0.1, 0.034, 4000.0, 4349.523184, -1034.154623),
    (0.25, 0.17, 4000.0, 3450.343003, -2000.887769),
    (0.0, -0.21, 2000.0, -30.04203835, 2228.79166),
    (0.0, 0.105, 2000.0, -58.87689376, -1799.707597),
]


def test_matches_an_independent_mf61_implementation(shipped):
    kappa, alpha, f_z, fx, fy = np.array(GOLDEN).T
    f = mf_forces(shipped, kappa, alpha, f_z, alpha_star=False)
    assert f.Fx == pytest.approx(fx, abs=1e-4)
    assert f.Fy == pytest.approx(fy, abs=1e-4)
    # the book's tan(alpha) changes Fy0 by ~0.1 % at 10 deg; Fx (combined: tan either way) not
    book = mf_forces(shipped, kappa, alpha, f_z)
    assert book.Fx == pytest.approx(fx, abs=1e-4)
    assert book.Fy == pytest.approx(fy, rel=5e-3)


def test_broadcasts(shipped):
    f = mf_forces(shipped, np.zeros((3, 1)), np.linspace(0, 0.2, 4), 4000.0)
    assert f.Fx.shape == f.Fy.shape == (3, 4)
