#!/usr/bin/env python3
"""Fit the controller's tyre forms to a TNO MF-Tyre .tir file and write them into a vehicle YAML.

    .venv/bin/python scripts/fit_tyres.py --tir config/tyres/pacejka_book_205_60r15.tir \\
        --vehicle gr86 --dry-run
    .venv/bin/python scripts/fit_tyres.py --tir FILE --vehicle NAME [--axle front|rear|both]

Prints the fit report (per axle: region, RMS and largest error, the drift point on the dry and the
wet surface, what the form cannot represent) and the new ``front_tyre:`` / ``rear_tyre:`` blocks;
without ``--dry-run`` it replaces those blocks in ``config/vehicle/<NAME>.yaml``, every other line
kept, after re-loading the result (written to a temp file, then renamed over the original).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import os
import re
import sys
import tempfile
from pathlib import Path

from drift_control.cli_args import positive
from drift_control.params import (ParamError, config_dir, load_surface, load_vehicle,
                                  vehicle_file)
from drift_control.tir import load_tir
from drift_control.tyre_fit import WET_MU, AxleFit, TyreFit, fit_tir


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--tir', required=True, help='TNO .tir tyre property file (MF 5.2/6.1)')
    parser.add_argument('--vehicle', required=True, help='name under config/vehicle')
    parser.add_argument('--config-dir', default=str(config_dir()))
    parser.add_argument('--axle', choices=('front', 'rear', 'both'), default='both')
    parser.add_argument('--wet-mu', type=positive, default=None,
                        help='wet friction scale of the report (default: surfaces.yaml wet)')
    parser.add_argument('--dry-run', action='store_true', help='report only, write nothing')
    args = parser.parse_args(argv)
    try:
        tyre = load_tir(args.tir)
        path = vehicle_file(args.vehicle, args.config_dir)
        vehicle = load_vehicle(path)
        wet_mu = args.wet_mu if args.wet_mu is not None else _wet_mu(args.config_dir)
        axles = ('front', 'rear') if args.axle == 'both' else (args.axle,)
        fit = fit_tir(tyre, vehicle, axles, wet_mu)
        source = _display_path(Path(args.tir), Path(args.config_dir))
        blocks = {f'{a.axle}_tyre': yaml_block(a, source, tyre.version)
                  for a in (fit.front, fit.rear) if a is not None}
        print(report(fit, args.vehicle, source))
        for block in blocks.values():
            print(block, end='')
        if not args.dry_run:
            text = path.read_text(encoding='utf-8')
            write_checked(path, replace_blocks(text, blocks), vehicle)
            print(f'wrote {", ".join(blocks)} into {path}')
    except ParamError as err:
        print(f'fit_tyres: {err}', file=sys.stderr)
        return 2
    except OSError as err:
        print(f'fit_tyres: {err}', file=sys.stderr)
        return 2
    except (ValueError, ArithmeticError) as err:   # a tyre whose forces are not finite
        print(f'fit_tyres: {args.tir}: the fit failed ({type(err).__name__}: {err})',
              file=sys.stderr)
        return 2
    return 0


def _wet_mu(config: str) -> float:
    surfaces = Path(config) / 'vehicle' / 'surfaces.yaml'
    return load_surface('wet', surfaces).mu if surfaces.is_file() else WET_MU


def _display_path(path: Path, config: Path) -> str:
    """The .tir path relative to the checkout (the config dir's parent) where it lies inside."""
    try:
        return str(path.resolve().relative_to(config.resolve().parent))
    except ValueError:
        return str(path)


# --- report -----------------------------------------------------------------------------------

def report(fit: TyreFit, vehicle: str, source: str) -> str:
    """The fit report as text: per axle the region, the errors, the drift point and the notes."""
    tyre = fit.tyre
    lines = [f'fit of {source} (MF {tyre.version}, FNOMIN {tyre.FNOMIN:.0f} N per tyre) to '
             f'{vehicle}: per axle a left tyre as in the file + a mirrored right tyre, each at '
             'half the axle load']
    for axle in (fit.front, fit.rear):
        if axle is not None:
            lines += _axle_report(axle)
    return '\n'.join(lines) + '\n'


def _axle_report(axle: AxleFit) -> list[str]:
    form = 'SimpleMF lateral + longitudinal' if axle.axle == 'front' else 'MF 5.2-style combined'
    lines = ['', f'{axle.axle} axle: {form}, fitted at mu 1 (least squares, force per load)']
    lines += [f'  region {name}: {region.describe()}' for name, region in axle.regions]
    lines.append('  errors over the region     RMS                max              (MF peak)')
    for s in axle.surfaces:
        for name in ('Fx', 'Fy'):
            e = getattr(s, name)
            lines.append(f'    mu {s.mu:<4g} {name}  {e.rms:8.0f} N {100 * e.rms_rel:5.1f} %   '
                         f'{e.max:8.0f} N {100 * e.max_rel:5.1f} %   ({e.peak:.0f} N)')
    d = axle.surfaces[0].drift
    lines.append(f'  drift point (30 deg drift, R 15 m): alpha {math.degrees(d.alpha):.1f} deg, '
                 f'kappa {d.kappa:g}, load {d.f_z:.0f} N')
    for s in axle.surfaces:
        lines.append(f'    mu {s.mu:<4g} ' + _point(s.drift))
    for c in axle.copied:
        lines.append(f'    mu {c.mu:<4g} ' + _point(c) + '  <- MF combined weights copied')
    lines.append('  notes:')
    lines += [f'    - {note}' for note in axle.notes]
    return lines


def _point(c) -> str:
    def one(name, mf, fit, rel):
        pct = 'n/a, ~0' if math.isnan(rel) else f'{100 * rel:+.1f} %'
        return f'{name} MF {mf:7.0f} N fit {fit:7.0f} N ({pct})'
    return (one('Fx', c.Fx_mf, c.Fx_fit, c.Fx_rel) + '   '
            + one('Fy', c.Fy_mf, c.Fy_fit, c.Fy_rel))


# --- the YAML blocks --------------------------------------------------------------------------

def yaml_block(axle: AxleFit, source: str, version: str) -> str:
    """The ``front_tyre:`` or ``rear_tyre:`` block (header line included) as YAML text."""
    dry, wet = axle.surfaces
    regions = '; '.join(f'{name} over {region.describe()}' for name, region in axle.regions)
    note = (f'fitted by scripts/fit_tyres.py to {source} (MF {version}, 2 tyres per axle) by '
            f'least squares at mu 1: {regions}. RMS error Fx {100 * dry.Fx.rms_rel:.1f}%, Fy '
            f'{100 * dry.Fy.rms_rel:.1f}% of the MF peak; at the 30 deg / 15 m drift point Fy '
            f'{_pct(dry.drift.Fy_rel)} dry, {_pct(wet.drift.Fy_rel)} at mu {wet.mu:g}'
            + ('.' if axle.axle == 'front' else f', Fx {_pct(dry.drift.Fx_rel)} dry, '
               f'{_pct(wet.drift.Fx_rel)} at mu {wet.mu:g}.'))
    lines = [f'{axle.axle}_tyre:', '  _source: >-'] + [f'    {t}' for t in _wrap(note, 94)]
    p = axle.params
    if axle.axle == 'front':
        for name in ('lateral', 'longitudinal'):
            mf = getattr(p, name)
            lines.append(f'  {name}: {{B: {_num(mf.B)}, C: {_num(mf.C)}, D: {_num(mf.D)}, '
                         f'E: {_num(mf.E)}}}')
    else:
        lines.append(f'  {"Fz0: " + _num(p.Fz0):<22}# nominal axle load [N]: 2 x LFZO x FNOMIN')
        lines += [f'  {f.name}: {_num(getattr(p, f.name))}' for f in dataclasses.fields(p)
                  if f.name != 'Fz0']
    return '\n'.join(lines) + '\n'


def _pct(rel: float) -> str:
    return 'n/a' if math.isnan(rel) else f'{100 * rel:+.1f}%'


def _num(value: float) -> str:
    """A float YAML reads back as a float: 6 significant digits, always with a dot."""
    text = f'{value:.6g}'
    mantissa, _, exponent = text.partition('e')
    if '.' not in mantissa:
        mantissa += '.0'
    return mantissa + ('e' + exponent if exponent else '')


def _wrap(text: str, width: int) -> list[str]:
    lines, line = [], ''
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f'{line} {word}' if line else word
    return lines + [line]


def replace_blocks(text: str, blocks: dict[str, str]) -> str:
    """``text`` with each top-level ``key:`` block replaced by ``blocks[key]``, nothing else.

    A block runs from its ``key:`` line to the next top-level key; blank lines and column-0
    comments just before that key stay (they belong to it). The header line is kept, with its
    comment, unless it carries an inline value. A key not in the file is appended.
    """
    lines = text.splitlines(keepends=True)
    for key, block in blocks.items():
        start = next((i for i, line in enumerate(lines)
                      if re.match(rf'{re.escape(key)}\s*:', line)), None)
        new = block.splitlines(keepends=True)
        if start is None:
            if lines and not lines[-1].endswith('\n'):
                lines[-1] += '\n'
            lines += ['\n'] + new
            continue
        end = next((i for i in range(start + 1, len(lines)) if re.match(r'[^\s#]', lines[i])),
                   len(lines))
        while end > start + 1 and (not lines[end - 1].strip() or lines[end - 1].startswith('#')):
            end -= 1
        inline = lines[start].split(':', 1)[1].strip()
        if not inline or inline.startswith('#'):
            new[0] = lines[start] if lines[start].endswith('\n') else lines[start] + '\n'
        lines[start:end] = new
    return ''.join(lines)


def write_checked(path: Path, text: str, before) -> None:
    """Write ``text`` over ``path`` only if it loads and differs from ``before`` only in tyres.

    Written to a temp file in the same directory and renamed over the original, so a failed or
    interrupted run leaves the old file whole.
    """
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as fh:
            fh.write(text)
        try:
            after = load_vehicle(Path(tmp))
        except ParamError as err:
            raise ParamError(f'{path}: the rewritten file would not load, left unchanged: '
                             f'{err}') from None
        if dataclasses.replace(before, front_tyre=after.front_tyre,
                               rear_tyre=after.rear_tyre) != after:
            raise ParamError(f'{path}: rewriting the tyre blocks changed other parameters; '
                             'file left unchanged')
        os.chmod(tmp, path.stat().st_mode & 0o7777)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


if __name__ == '__main__':
    sys.exit(main())
