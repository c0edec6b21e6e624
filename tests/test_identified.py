"""Campaigns on identified cars: each plant's controller model from the plant's own log."""
import shlex
from pathlib import Path

import pytest

from drift_sim import campaign, identified
from drift_sim.campaign import campaign_jobs
from drift_sim.identified import (IdentificationFailed, REAR_FIT, identified_car,
                                  identified_name, sysid_overrides)


def test_the_identification_drive_is_the_draw_on_the_dry_pad():
    assert sysid_overrides('gr86', None, None) == ()
    steady = campaign_jobs(['steady_dry'], ['gr86'], [0], plants=[4], plant_seed=1)[0]
    assert sysid_overrides('gr86', 4, 1) == steady.overrides   # the same plant, same road
    assert sysid_overrides('gr86', 5, 1) != steady.overrides
    assert identified_name('gr86', 4) == 'gr86_id4' and identified_name('gr86', None) == 'gr86_id'


def test_identified_jobs_are_keyed_apart_and_replay_on_the_identified_car(tmp_path, monkeypatch):
    plain = campaign_jobs(['steady_dry'], ['gr86'], [0], plants=[2])[0]
    job = campaign_jobs(['steady_dry'], ['gr86'], [0], plants=[2], identify=True)[0]
    assert job.overrides == plain.overrides and job.key != plain.key
    assert job.row()['identify'] is True and 'identify' not in plain.row()
    monkeypatch.setattr(identified, 'identified_car',
                        lambda *a: (str(tmp_path / 'cfg'), 'gr86_id2'))
    monkeypatch.setattr(campaign, 'run_seed', lambda *a, **k: ({'spun': False}, 1.0))
    row = campaign.run_job(job)
    assert row['identified'] == {'vehicle': 'gr86_id2', 'config': str(tmp_path / 'cfg')}
    words = shlex.split(row['replay'])
    assert words[words.index('--vehicle') + 1] == 'gr86_id2'
    assert words[words.index('--config-dir') + 1] == str(tmp_path / 'cfg')


def test_a_car_is_identified_once_and_the_rear_alone_when_the_front_cannot_be(tmp_path,
                                                                             monkeypatch):
    monkeypatch.setenv('DRIFT_IDENTIFIED_DIR', str(tmp_path / 'cache'))
    calls = []

    def fake(script, *args):
        calls.append((Path(script).name, args))
        if Path(script).name == 'identify.py':
            if '--fit' not in args:
                raise IdentificationFailed('identify.py: front_tyre.lateral.C: never near')
            out = Path(args[args.index('--out') + 1])
            out.write_text(out.with_name('gr86.yaml').read_text())
    monkeypatch.setattr(identified, '_script', fake)
    config, name = identified_car('gr86', 3, 0)
    assert name == 'gr86_id3' and (Path(config) / 'vehicle' / 'gr86_id3.yaml').is_file()
    assert (Path(config) / 'sim' / 'plants' / 'gr86_id3.yaml').is_file()   # the same plant
    scripts = [c[0] for c in calls]
    assert scripts == ['sysid_drive.py', 'identify.py', 'identify.py', 'build_maps.py',
                       'build_maps.py']
    drive = calls[0][1]
    assert [drive[i + 1] for i, w in enumerate(drive) if w == '--set'] == \
        list(sysid_overrides('gr86', 3, 0))
    refit = calls[2][1]
    assert refit[refit.index('--fit') + 1] == ','.join(REAR_FIT)
    calls.clear()
    assert identified_car('gr86', 3, 0) == (config, name) and not calls   # kept, not redone
    assert identified_car('gr86', 4, 0)[0] != config                      # another plant


def test_a_plant_that_cannot_be_identified_is_that_run_s_error(tmp_path, monkeypatch):
    monkeypatch.setenv('DRIFT_IDENTIFIED_DIR', str(tmp_path / 'cache'))

    def fake(script, *args):
        if Path(script).name == 'identify.py':
            raise IdentificationFailed('identify.py: rear_tyre.pDy1: no sideslip beyond the '
                                       'grip limit in the log')
    monkeypatch.setattr(identified, '_script', fake)
    with pytest.raises(IdentificationFailed, match='no sideslip beyond'):
        identified_car('gr86', 1, 0)
    assert not list((tmp_path / 'cache').glob('*/ready'))
