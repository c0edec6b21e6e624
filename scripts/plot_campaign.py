#!/usr/bin/env python3
"""Figures of a campaign store: pass rates, error histograms, and which plant ranges fail.

    .venv/bin/python scripts/plot_campaign.py runs/campaign.jsonl --out runs/campaign_figures

Writes three PNGs into ``--out``:

- ``pass_rate.png``: held runs per scenario and vehicle, with the Wilson 95 % interval;
- ``errors.png``: sideslip RMS error and largest lateral error of the held runs, per scenario,
  one histogram per vehicle;
- ``failure_map.png``: per vehicle, the share of runs not ending as the scenario expects in each
  fifth of every randomized parameter's range (``config/sim/populations/<vehicle>.yaml``):
  which ranges fail. Only runs on drawn plants count there.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib
import numpy as np

from drift_control.cli_args import output_problem
from drift_control.params import ParamError, config_dir
from drift_sim.population import load_population
from drift_sim.store import RunStore
from drift_sim.sweep import HELD, as_expected, campaign_summary, outcome

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402  (after the backend is chosen)

BINS = 5   # each parameter's range in fifths: enough runs per cell at 100 plants


def pass_rates(summary: dict, path: Path) -> None:
    """Bars of the held share per scenario, one bar per vehicle, with the 95 % interval."""
    groups = summary['groups']
    scenarios = sorted({g['scenario'] for g in groups})
    vehicles = sorted({g['vehicle'] for g in groups})
    width = 0.8 / len(vehicles)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.3 * len(scenarios) + 2.0), 4.0))
    for i, vehicle in enumerate(vehicles):
        mine = {g['scenario']: g for g in groups if g['vehicle'] == vehicle}
        x = np.array([k for k, sc in enumerate(scenarios) if sc in mine], dtype=float)
        rate = np.array([mine[sc]['pass_rate'] for sc in scenarios if sc in mine])
        lo = np.array([mine[sc]['ci95'][0] for sc in scenarios if sc in mine])
        hi = np.array([mine[sc]['ci95'][1] for sc in scenarios if sc in mine])
        bars = ax.bar(x + (i - (len(vehicles) - 1) / 2) * width, 100 * rate, width,
                      yerr=100 * np.vstack([rate - lo, hi - rate]), capsize=3, label=vehicle,
                      color=f'C{i}')
        for bar, sc in zip(bars, [sc for sc in scenarios if sc in mine]):
            ax.annotate(f"{mine[sc]['held']}/{mine[sc]['runs']}",
                        (bar.get_x() + bar.get_width() / 2, 1.0), ha='center', fontsize=7,
                        color='white', va='bottom')
    labels = [sc + ('\n(paper: spun)' if any(g['expect_spin'] for g in groups
                                             if g['scenario'] == sc) else '')
              for sc in scenarios]
    ax.set_xticks(range(len(scenarios)), labels, rotation=20, ha='right', fontsize=8)
    ax.set_ylabel('held [%] (95 % Wilson interval)')
    ax.set_ylim(0, 118)    # room above 100 % for the legend
    ax.legend(fontsize=8, loc='upper center', ncol=len(vehicles))
    ax.set_title(f"Pass rate, {summary['runs']} runs")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def error_histograms(rows: list[dict], path: Path) -> None:
    """Sideslip RMS error and max |e_y| of the held runs, per scenario, a histogram per car."""
    held = [r for r in rows if outcome(r['metrics']) == HELD]
    scenarios = sorted({r['scenario'] for r in rows})
    vehicles = sorted({r['vehicle'] for r in rows})
    metrics = (('beta_rms_error_deg', 'sideslip RMS error [deg]'),
               ('max_abs_e_y_m', 'max |e_y| after the entry [m]'))
    fig, axes = plt.subplots(2, len(scenarios), figsize=(2.6 * len(scenarios) + 1.0, 5.0),
                             squeeze=False)
    for col, sc in enumerate(scenarios):
        for row, (key, label) in enumerate(metrics):
            ax = axes[row, col]
            values = {v: [r['metrics'][key] for r in held if r['scenario'] == sc
                          and r['vehicle'] == v and r['metrics'].get(key) is not None]
                      for v in vehicles}
            pooled = [x for xs in values.values() for x in xs]
            if pooled:
                edges = np.histogram_bin_edges(pooled, bins=min(20, max(5, len(pooled) // 5)))
                for i, (v, xs) in enumerate(values.items()):   # one colour per car throughout
                    if xs:
                        ax.hist(xs, bins=edges, alpha=0.6, label=v, color=f'C{i}')
            else:
                ax.text(0.5, 0.5, 'no held run\nwith this metric', ha='center', va='center',
                        transform=ax.transAxes, fontsize=8)
            ax.set_xlabel(label, fontsize=8)
            ax.tick_params(labelsize=7)
            if row == 0:
                ax.set_title(sc, fontsize=9)
    axes[0, 0].set_ylabel('held runs')
    axes[1, 0].set_ylabel('held runs')
    handles = {label: h for ax in axes.flat for h, label in zip(*ax.get_legend_handles_labels())}
    if handles:
        fig.legend(list(handles.values()), list(handles), fontsize=8, loc='upper center',
                   ncol=len(handles))
    fig.tight_layout(rect=(0, 0, 1, 0.93))   # the legend above the titles
    fig.savefig(path, dpi=120)
    plt.close(fig)


def failure_map(rows: list[dict], path: Path, config=None) -> bool:
    """Per vehicle, the failure share in each fifth of each randomized parameter's range."""
    drawn = [r for r in rows if r.get('draw') is not None and r.get('values')]
    vehicles = sorted({r['vehicle'] for r in drawn})
    if not vehicles:
        return False
    fig, axes = plt.subplots(1, len(vehicles), figsize=(6.5 * len(vehicles), 6.0),
                             squeeze=False)
    for ax, vehicle in zip(axes[0], vehicles):
        ranges = load_population(vehicle, config=config).ranges
        mine = [r for r in drawn if r['vehicle'] == vehicle]
        failed = np.array([not as_expected(r['metrics']) for r in mine])
        share = np.full((len(ranges), BINS), np.nan)
        count = np.zeros((len(ranges), BINS), dtype=int)
        for i, rng in enumerate(ranges):
            u = np.array([r['values'].get(rng.name, np.nan) for r in mine], dtype=float)
            span = (rng.high - rng.low) or 1.0
            cell = np.clip(((u - rng.low) / span * BINS).astype(int, copy=False), 0, BINS - 1)
            for b in range(BINS):
                sel = np.isfinite(u) & (cell == b)
                count[i, b] = sel.sum()
                if count[i, b]:
                    share[i, b] = failed[sel].mean()
        ax.set_facecolor('0.85')   # grey: no run drew a value in that fifth
        image = ax.imshow(100 * share, cmap='Reds', vmin=0, vmax=100, aspect='auto')
        for (i, b), n in np.ndenumerate(count):
            if n:
                ax.text(b, i, f'{100 * share[i, b]:.0f}%\n{n}', ha='center', va='center',
                        fontsize=6)
        ax.set_yticks(range(len(ranges)),
                      [f'{r.name} [{_fmt(r.low, r.kind)}, {_fmt(r.high, r.kind)}]'
                       for r in ranges], fontsize=7)
        ax.set_xticks(range(BINS), [f'{k + 1}/{BINS}' for k in range(BINS)], fontsize=7)
        ax.set_xlabel('fifth of the range (low to high); cell: failure share, runs; grey: none')
        ax.set_title(f'{vehicle}: {int(failed.sum())} of {len(mine)} runs not as expected',
                     fontsize=9)
        fig.colorbar(image, ax=ax, label='not as expected [%]', shrink=0.8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def _fmt(value: float, kind: str) -> str:
    return f'{100 * value:+.0f}%' if kind == 'relative' else f'{value:g}'


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('store', help='a campaign store (scripts/campaign.py --store)')
    parser.add_argument('--out', required=True, help='directory for the PNGs')
    parser.add_argument('--config-dir', default=str(config_dir()),
                        help='where the populations of the failure map live')
    args = parser.parse_args(argv)
    try:
        if not Path(args.store).is_file():
            raise ParamError(f'{args.store}: no such store')
        rows = RunStore(args.store).rows()
        if not rows:
            raise ParamError(f'{args.store}: no runs')
        problem = output_problem(args.out, [args.store], directory=True)
        if problem is not None:
            raise ParamError(problem)
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        try:
            pass_rates(campaign_summary(rows), out / 'pass_rate.png')
            error_histograms(rows, out / 'errors.png')
            mapped = failure_map(rows, out / 'failure_map.png', args.config_dir)
        except (KeyError, TypeError) as err:
            raise ParamError(f'{args.store}: a row is not a finished run of a campaign '
                             f'({type(err).__name__}: {err})') from None
    except (ParamError, OSError) as err:
        print(f'plot_campaign: {err}', file=sys.stderr)
        return 2
    print(f'wrote {out}/pass_rate.png, errors.png'
          + (', failure_map.png' if mapped else ' (no drawn plants: no failure map)'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
