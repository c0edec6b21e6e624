"""Bring your own car: a generated vehicle in a copied config dir, driven with the documented
commands only (docs/bring_your_own_car.md): maps, a headless run, a run of the node graph.

The generated car is the default car made lighter and shorter (a different car, not a copy);
its maps go to the copy's own maps dir, and the checkout's maps/ must stay as it was.
"""
import os
import shutil
import subprocess
import sys

import pytest
import yaml

from drift_control.assembly import maps_dir
from drift_control.params import config_dir, default_vehicle
from drift_sim.params import plant_file

pytest.importorskip('drift_msgs.msg')
pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = config_dir().parent
CAR = 'generated_coupe'


def _generate(cfg):
    """A vehicle YAML and its plant: the default car, 10 % lighter, 5 % shorter wheelbase."""
    vehicle = yaml.safe_load((cfg / 'vehicle' / f'{default_vehicle()}.yaml').read_text())
    vehicle.update(m=0.9 * vehicle['m'], I_z=0.82 * vehicle['I_z'], L=0.95 * vehicle['L'],
                   a=0.95 * vehicle['a'])
    vehicle['rear_tyre']['Fz0'] *= 0.9
    (cfg / 'vehicle' / f'{CAR}.yaml').write_text(yaml.safe_dump(vehicle, sort_keys=False))
    plant = yaml.safe_load(plant_file(default_vehicle(), cfg).read_text())
    plant['body'].update(m=0.9 * plant['body']['m'], I_z=0.82 * plant['body']['I_z'],
                         L=0.95 * plant['body']['L'], a=0.95 * plant['body']['a'])
    (cfg / 'sim' / 'plants' / f'{CAR}.yaml').write_text(yaml.safe_dump(plant, sort_keys=False))


def _run(*argv, timeout=300):
    proc = subprocess.run([sys.executable, *map(str, argv)], cwd=REPO, capture_output=True,
                          text=True, timeout=timeout,
                          env={**os.environ, 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


def test_a_generated_car_in_a_copied_config_dir_is_drivable(tmp_path):
    cfg = tmp_path / 'config'
    shutil.copytree(config_dir(), cfg)
    _generate(cfg)
    before = sorted((p.relative_to(maps_dir()), p.stat().st_mtime_ns)
                    for p in maps_dir().rglob('*'))

    out = _run('scripts/build_maps.py', '--config-dir', cfg, '--vehicle', CAR, '--surface',
               'dry', '--beta-deg', '0:36:2', '--radius', '12:18:1', '--jobs', '2')
    assert (tmp_path / 'maps' / CAR / 'dry.npz').is_file(), out
    assert sorted((p.relative_to(maps_dir()), p.stat().st_mtime_ns)
                  for p in maps_dir().rglob('*')) == before, "the checkout's maps/ untouched"

    metrics = yaml.safe_load(_run('scripts/simulate.py', '--config-dir', cfg, '--vehicle', CAR,
                                  '--scenario', 'steady_dry', '--set', 'duration=8', '--quiet'))
    assert metrics['vehicle'] == CAR and metrics['sim_duration_s'] > 7.9
    assert metrics['solve_time_ms_p50'] is not None, 'the NMPC ran'

    out = _run('scripts/run_stack.py', '--config-dir', cfg, '--vehicle', CAR, '--scenario',
               'steady_dry', '--sim-duration', '2', '--duration', '120', '--bag',
               tmp_path / 'bag', '--domain-id', '123', '--no-summary', timeout=180)
    assert '[launch] stopped (node-exit)' in out, out[-3000:]
    assert f'vehicle {CAR}' in out and f'{CAR}, full on dry' in out, out[-3000:]
