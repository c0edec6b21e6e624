"""Campaigns: jobs and their hashes, the run store, the summary, scripts/campaign.py, and a
2-worker Ray campaign that is interrupted and resumed (Ray is started once for this module)."""
import dataclasses
import json
import math
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time

import pytest

from drift_control.assembly import maps_dir
from drift_control.params import ParamError, config_dir
from drift_sim.campaign import Job, campaign_jobs, code_version, config_digest, run_jobs
from drift_sim.store import RunStore
from drift_sim.sweep import (ERROR, HELD, LOST, SPUN, TRIPPED, campaign_summary, format_campaign,
                             parse_plants, wilson_interval)

from conftest import REPO, load_script

# short runs with metric windows inside them: 1 s of an established drift
SHORT = ['duration=1.0', 'metrics.transient_end=0.5', 'metrics.steady=[[0.5, 1.0]]']


def test_wilson_interval_holds_the_pass_rate():
    """Rounding never leaves the estimate outside its interval (6/6 gave an upper bound of
    0.9999999999999999, a negative error bar in the pass-rate figure)."""
    for n in range(1, 201):
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert 0.0 <= lo <= k / n <= hi <= 1.0, (k, n)


def test_wilson_interval_against_the_closed_form():
    lo, hi = wilson_interval(8, 10)
    assert (lo, hi) == (pytest.approx(0.4902, abs=1e-4), pytest.approx(0.9433, abs=1e-4))
    assert wilson_interval(0, 10) == (0.0, pytest.approx(0.2775, abs=1e-4))
    assert wilson_interval(10, 10) == (pytest.approx(0.7225, abs=1e-4), 1.0)
    lo3, hi3 = wilson_interval(3, 10)
    assert (lo3, hi3) == (pytest.approx(1 - wilson_interval(7, 10)[1]),
                          pytest.approx(1 - wilson_interval(7, 10)[0]))
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_jobs_go_plant_by_plant_through_every_scenario_and_car_with_distinct_hashes():
    jobs = campaign_jobs(['steady_dry', 'steady_wet'], ['m3_competition', 'gr86'], [0, 1],
                         plants=2, overrides=['duration=2'])
    assert len(jobs) == 16 and len({j.key for j in jobs}) == 16
    assert [(j.scenario, j.vehicle, j.draw, j.seed) for j in jobs[:5]] == [
        ('steady_dry', 'm3_competition', 0, 0), ('steady_dry', 'gr86', 0, 0),
        ('steady_wet', 'm3_competition', 0, 0), ('steady_wet', 'gr86', 0, 0),
        ('steady_dry', 'm3_competition', 0, 1)]
    assert all(j.overrides[0] == 'duration=2' and len(j.overrides) > 30 for j in jobs)
    nominal = campaign_jobs(['steady_dry'], ['gr86'], [4])
    digest = config_digest()
    assert nominal == [Job('steady_dry', 'gr86', 4, config_digest=digest)]
    assert nominal[0].key == Job('steady_dry', 'gr86', 4, values={'x': 1.0},
                                 config_digest=digest).key
    assert nominal[0].key != Job('steady_dry', 'gr86', 5, config_digest=digest).key


def test_listed_plant_draws_are_those_draws_of_a_larger_campaign():
    """``--plants 2-3`` runs draws 2 and 3 exactly as ``--plants 4`` does: the same store keys,
    so a campaign extends (or splits across machines) without running its first draws again."""
    whole = campaign_jobs(['steady_dry'], ['gr86'], [0], plants=4)
    part = campaign_jobs(['steady_dry'], ['gr86'], [0], plants=parse_plants('2-3'))
    assert [j.key for j in part] == [j.key for j in whole[2:]]
    assert [j.draw for j in part] == [2, 3]
    assert parse_plants('3') == [0, 1, 2] and parse_plants('0') == []
    assert parse_plants('5,1') == [1, 5]


def test_the_configuration_counts_by_its_values_not_its_text_or_place(tmp_path):
    """A copy of the configuration with another comment keys its runs as the original does (a
    store resumes across it); a changed value keys them anew (they are run, not taken from
    the store)."""
    copy = tmp_path / 'config'
    shutil.copytree(config_dir(), copy)
    (tmp_path / 'maps').symlink_to(maps_dir())
    nmpc = copy / 'nmpc.yaml'
    nmpc.write_text('# a comment of the copy\n' + nmpc.read_text())
    key = lambda config: campaign_jobs(['steady_dry'], ['gr86'], [0], plants=1,
                                       config=config)[0].key
    assert config_digest(copy) == config_digest() and key(str(copy)) == key(None)
    text = nmpc.read_text()
    nmpc.write_text(text.replace('disturbance_gain: 0.02', 'disturbance_gain: 0.03'))
    assert text != nmpc.read_text(), 'the value to change is in the file'
    assert config_digest(copy) != config_digest() and key(str(copy)) != key(None)
    changed = config_digest(copy)
    (copy / 'sim' / 'notes.yaml').write_text('a: [1,\n')   # read by no run, not valid YAML
    assert config_digest(copy) != changed, 'counted by its bytes, not refused'


def test_a_row_names_the_code_it_ran_on_which_does_not_key_it():
    job = campaign_jobs(['steady_dry'], ['gr86'], [0])[0]
    assert job.row()['code'] == code_version()
    assert dataclasses.replace(job, code='another').key == job.key


def test_a_replay_command_is_the_job_for_simulate_py():
    job = campaign_jobs(['alternating_dry'], ['gr86'], [3], plants=1, plant_seed=2)[0]
    words = shlex.split(job.replay_command())
    assert words[1] == 'scripts/simulate.py'
    assert words[words.index('--vehicle') + 1] == 'gr86' and words[words.index('--seed') + 1] == '3'
    assert [words[i + 1] for i, w in enumerate(words) if w == '--set'] == list(job.overrides)


def test_jobs_through_the_sensors_and_estimator_carry_them_into_key_row_and_replay():
    plain = campaign_jobs(['steady_dry'], ['gr86'], [0], plants=1)[0]
    sensed = campaign_jobs(['steady_dry'], ['gr86'], [0], plants=1, sensors='realistic',
                           estimator='ekf')[0]
    assert sensed.overrides == plain.overrides and sensed.key != plain.key
    assert (sensed.row()['sensors'], sensed.row()['estimator']) == ('realistic', 'ekf')
    assert 'sensors' not in plain.row()
    assert sensed.sensor_set and sensed.row()['sensor_set'] == list(sensed.sensor_set)
    words = shlex.split(sensed.replay_command())
    assert words[words.index('--sensors') + 1] == 'realistic'
    assert words[words.index('--estimator') + 1] == 'ekf'
    # the draw's sensor noise rides along: the replay runs the same sensor units
    assert [words[i + 1] for i, w in enumerate(words) if w == '--sensor-set'] == \
        list(sensed.sensor_set)
    with pytest.raises(ParamError, match="'kalman' is not one of"):
        campaign_jobs(['steady_dry'], ['gr86'], [0], sensors='realistic', estimator='kalman')


@pytest.mark.parametrize('scenario, vehicle, message', [
    ('no_such', 'gr86', 'known scenarios: alternating_dry'),
    ('steady_dry', 'no_such', 'known vehicles: gr86, m3_competition')])
def test_unknown_scenarios_and_vehicles_are_refused_before_any_run(scenario, vehicle, message):
    with pytest.raises(ParamError, match=message):
        campaign_jobs([scenario], [vehicle], [0])


def _row(key, outcome_metrics, scenario='steady_dry', vehicle='gr86', draw=0):
    return {'key': key, 'scenario': scenario, 'vehicle': vehicle, 'seed': 0, 'draw': draw,
            'outcome': 'x', 'replay': f'simulate {key}', 'metrics': outcome_metrics}


def test_the_store_keeps_finished_runs_and_drops_a_half_written_line(tmp_path):
    path = tmp_path / 'runs.jsonl'
    store = RunStore(path)
    store.add(_row('a', {}) | {'outcome': HELD})
    store.add(_row('b', {}) | {'outcome': ERROR})
    with open(path, 'a') as fh:
        fh.write('{"key": "c", "outc')          # killed while writing
    again = RunStore(path)
    assert 'a' in again and 'b' not in again       # an error is run again
    assert len(again) == 2 and again.get('b')['outcome'] == ERROR
    again.add(_row('b', {}) | {'outcome': HELD})
    lines = path.read_text().splitlines()
    assert [json.loads(line)['key'] for line in lines] == ['a', 'b', 'b']
    assert 'b' in RunStore(path)                  # the newest row of a key wins
    path.write_text(lines[0] + '\n[1, 2]\n')
    with pytest.raises(ParamError, match=r'runs.jsonl:2: not a row'):
        RunStore(path)


def test_the_store_keeps_a_whole_last_row_without_its_newline(tmp_path):
    path = tmp_path / 'runs.jsonl'
    path.write_text(json.dumps(_row('a', {}) | {'outcome': HELD}) + '\n'
                    + json.dumps(_row('b', {}) | {'outcome': HELD}))   # edited by hand
    store = RunStore(path)
    assert 'a' in store and 'b' in store
    store.add(_row('c', {}) | {'outcome': HELD})
    assert [json.loads(line)['key'] for line in path.read_text().splitlines()] == ['a', 'b', 'c']
    assert len(RunStore(path)) == 3


def test_the_summary_counts_each_failure_mode_with_when_and_where():
    held = {'spun': False, 'supervisor_trip_s': None, 'beta_rms_error_deg': 0.3,
            'max_abs_e_y_m': 0.8, 'event_t_s': 30.0, 'event_s_m': 200.0}
    rows = [_row('h1', held), _row('h2', held | {'max_abs_e_y_m': 1.2}),
            _row('s', {'spun': True, 'spin_time_s': 7.0, 'event_t_s': 7.0, 'event_s_m': 60.0}),
            _row('t', {'spun': False, 'supervisor_trip_s': 4.5, 'event_t_s': 4.5,
                       'event_s_m': 40.0}),
            _row('l', held | {'max_abs_e_y_m': 9.0}),
            _row('e', {'error': 'RuntimeError: boom'}),
            _row('m', held, vehicle='m3_competition')]
    summary = campaign_summary(rows, worst=3)
    gr86, m3 = summary['groups']
    assert (gr86['vehicle'], gr86['runs'], gr86['held']) == ('gr86', 6, 2)
    assert gr86['ci95'] == list(wilson_interval(2, 6))
    assert gr86['max_abs_e_y_m']['max'] == 1.2            # over the held runs only
    modes = gr86['failure_modes']
    assert set(modes) == {SPUN, TRIPPED, LOST, ERROR}
    assert modes[SPUN]['when_s']['p50'] == 7.0 and modes[SPUN]['where_s_m']['p50'] == 60.0
    assert modes[ERROR]['errors'] == ['RuntimeError: boom']
    assert (m3['runs'], m3['held'], m3['ci95']) == (1, 1, list(wilson_interval(1, 1)))
    assert [w['replay'] for w in summary['worst']] == ['simulate e', 'simulate s', 'simulate t']
    text = format_campaign(summary)
    assert '| steady_dry | gr86 | 6 | 2 | 33 % (10-70 %) |' in text
    assert 'spun at 7.0 s, s = 60 m' in text and '`simulate s`' in text


# --- scripts/campaign.py: bad input is one line and exit 2, never a traceback ------------------

def _free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


@pytest.fixture
def broken_population(tmp_path):
    config = tmp_path / 'config'
    shutil.copytree(REPO / 'config', config)
    (config / 'sim' / 'populations' / 'gr86.yaml').write_text(
        'parameters:\n  mass: {keys: [plant.body.m], relative: [-0.1], why: x}\n')
    return config


@pytest.mark.parametrize('argv, message', [
    (['--scenario', 'no_such'], "scenario 'no_such'"),
    (['--vehicle', 'no_such'], "vehicle 'no_such'"),
    (['--seeds', '3-1'], 'seeds'),
    (['--plants', '-3'], "plants: '-3' is not N or N-M"),
    (['--plants', '9-2'], "plants: '9-2' is not a range of plants >= 0"),
    (['--jobs', '0'], '--jobs: expected an integer >= 1'),
    (['--set', 'plant.body.mass=3'], "unknown key(s) ['mass']"),
    (['--address', f'127.0.0.1:{_free_port()}'], 'cannot reach it'),
    (['--address', 'nowhere'], 'expected host:port'),
    (['--sensors', 'no_such'], "sensors 'no_such'"),
    (['--estimator', 'ekf'], 'estimator: needs sensors'),
    (['--sensors', 'realistic', '--estimator', 'kalman'], "'kalman' is not one of"),
    (['--plants', '1', '--vehicle', 'gr86', '--config-dir', 'BROKEN'],
     'gr86.yaml: parameters.mass.relative: expected [low, high]'),
])
def test_bad_input_is_one_line_and_exit_2(argv, message, tmp_path, capsys, broken_population):
    argv = [str(broken_population) if a == 'BROKEN' else a for a in argv]
    rc = load_script('campaign').main(['--store', str(tmp_path / 's.jsonl'), *argv])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count('\n') == 1 and err.startswith('campaign: ') and message in err, err
    assert not (tmp_path / 's.jsonl').exists()


# --- running: a 2-worker Ray campaign, interrupted and resumed ---------------------------------

@pytest.fixture(scope='module')
def ray_pool():
    pytest.importorskip('ray')
    pytest.importorskip('drift_control.nmpc')
    from drift_sim.executor import RayExecutor
    with RayExecutor(workers=2) as pool:
        yield pool


@pytest.mark.slow
def test_a_ray_campaign_stores_every_run_and_resumes_without_redoing_any(tmp_path, ray_pool):
    jobs = campaign_jobs(['drift_hold_dry'], ['m3_competition', 'gr86'], [0], plants=3,
                         overrides=SHORT)
    path = tmp_path / 'runs.jsonl'
    first = []

    def interrupt_after_two(row):
        first.append(row['key'])
        if len(first) == 2:
            raise KeyboardInterrupt          # Ctrl-C, between two finished runs

    with pytest.raises(KeyboardInterrupt):
        run_jobs(jobs, ray_pool, RunStore(path), progress=False, on_row=interrupt_after_two)
    assert len(path.read_text().splitlines()) == 2 and all(k in RunStore(path) for k in first)

    second = []
    rows = run_jobs(jobs, ray_pool, RunStore(path), progress=False,
                    on_row=lambda row: second.append(row['key']))
    assert sorted(second) == sorted(j.key for j in jobs if j.key not in first)
    assert len(path.read_text().splitlines()) == len(jobs)      # nothing ran twice
    assert [r['key'] for r in rows] == [j.key for j in jobs]
    for job, row in zip(jobs, rows):
        assert (row['vehicle'], row['draw'], row['overrides'], row['values']) == (
            job.vehicle, job.draw, list(job.overrides), job.values)
        assert row['metrics']['vehicle'] == job.vehicle and row['outcome'] != ERROR
        assert row['metrics']['sim_duration_s'] == pytest.approx(1.0, abs=0.02)
    # the drawn plants are different cars: the same seed tracks differently on each
    assert len({r['metrics']['beta_rms_error_deg'] for r in rows}) == len(rows)

    summary = campaign_summary(rows)
    assert [(g['vehicle'], g['runs']) for g in summary['groups']] == [('gr86', 3),
                                                                      ('m3_competition', 3)]
    assert summary['held'] == sum(r['outcome'] == HELD for r in rows)
    assert all(math.isfinite(r['metrics']['beta_rms_error_deg']) for r in rows)
    assert run_jobs(jobs, ray_pool, RunStore(path), progress=False,
                    on_row=pytest.fail) == rows   # a finished campaign runs nothing


def test_a_task_s_own_error_comes_back_from_ray_as_itself(ray_pool):
    (item, result), = ray_pool.map_unordered(json.loads, ['{not json'])   # raises in the task
    assert item == '{not json' and isinstance(result, json.JSONDecodeError)
    assert str(result).startswith('Expecting property name')   # the reason, not Ray's wrapper


@pytest.mark.slow
def test_an_interrupted_campaign_writes_no_summary_and_the_same_command_finishes_it(tmp_path):
    pytest.importorskip('drift_control.nmpc')
    store, summary = tmp_path / 'runs.jsonl', tmp_path / 'summary.md'
    argv = ['--scenario', 'drift_hold_dry', '--vehicle', 'gr86', '--seeds', '0-2', '--jobs',
            '1', '--quiet', '--store', str(store), '--summary', str(summary)]
    for item in SHORT:
        argv += ['--set', item]
    proc = subprocess.Popen([sys.executable, str(REPO / 'scripts' / 'campaign.py'), *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not (store.exists() and store.read_text().count('\n') >= 1):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert 'interrupted' in err and 'Traceback' not in err
    done = len(store.read_text().splitlines())
    assert 1 <= done < 3 and not summary.exists()

    assert load_script('campaign').main(argv) == 0
    assert len(store.read_text().splitlines()) == 3
    assert '| drift_hold_dry | gr86 | 3 |' in summary.read_text()


def test_figures_of_a_store_with_drawn_plants(tmp_path):
    from drift_sim.population import draw, load_population
    population = load_population('gr86')
    store = RunStore(tmp_path / 'runs.jsonl')
    for index in range(12):
        spun = index % 3 == 0
        metrics = {'spun': spun, 'spin_time_s': 5.0 if spun else None, 'event_t_s': 5.0,
                   'event_s_m': 50.0, 'beta_rms_error_deg': 0.4 + 0.01 * index,
                   'max_abs_e_y_m': 0.5 + 0.02 * index}
        store.add(_row(f'k{index}', metrics, draw=index)
                  | {'values': draw(population, index).values})
    plot = load_script('plot_campaign')
    out = tmp_path / 'figures'
    assert plot.main([str(tmp_path / 'runs.jsonl'), '--out', str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ['errors.png', 'failure_map.png',
                                                     'pass_rate.png']
    assert plot.main([str(tmp_path / 'none.jsonl'), '--out', str(out)]) == 2
