"""A tool never writes over or into its inputs, and a bad output path is one line before the work."""

import pytest

from conftest import load_script
from drift_control.cli_args import output_problem, write_text


def _bag(tmp_path):
    bag = tmp_path / 'bag'
    bag.mkdir()
    (bag / 'metadata.yaml').write_text('rosbag2_bagfile_information: {}\n')
    (bag / 'bag_0.mcap').write_bytes(b'evidence')
    return bag


def test_output_problem_names_each_way_a_path_cannot_take_an_output(tmp_path):
    bag, store = _bag(tmp_path), tmp_path / 'runs.jsonl'
    store.write_text('{"key": "a"}\n')
    assert 'is inside the input' in output_problem(bag / 'metadata.yaml', [bag])
    assert 'is inside the input' in output_problem(bag / 'sub', [bag], directory=True)
    assert 'is the input' in output_problem(bag, [bag], directory=True)
    assert 'is the input' in output_problem(store, [store])
    assert 'is a directory' in output_problem(bag)
    assert 'is not a directory' in output_problem(store, directory=True)
    assert 'cannot be written' in output_problem(store / 'below' / 'x.json')   # under a file
    assert output_problem(tmp_path / 'new' / 'deeper' / 'out.json', [bag, store]) is None
    assert output_problem(store) is None                   # appended to: still fine, unchanged
    assert not (tmp_path / 'new').exists()                 # the probe leaves nothing behind
    assert store.read_text() == '{"key": "a"}\n'
    assert 'cannot be written' in write_text(bag, 'x')
    assert write_text(tmp_path / 'a' / 'b.txt', 'x') is None


def test_tools_refuse_to_write_over_or_into_their_inputs(tmp_path, capsys):
    bag, store = _bag(tmp_path), tmp_path / 'runs.jsonl'
    store.write_text('')
    before = {p.name: p.read_bytes() for p in bag.iterdir()}
    assert load_script('replay').main([str(bag), '--rerun', '--json',
                                       str(bag / 'metadata.yaml')]) == 2
    assert load_script('report').main([str(bag), '--out', str(bag)]) == 2
    assert load_script('campaign').main(['--scenario', 'steady_dry', '--store', str(store),
                                         '--summary', str(store)]) == 2
    assert load_script('seed_sweep').main(['--scenario', 'steady_dry', '--store', str(store),
                                           '--json', str(store)]) == 2
    from drift_tools.operator import main as drift
    assert drift(['bag', 'slice', str(bag), str(bag / 'part')]) == 2
    assert drift(['bag', 'export', str(bag), str(bag / 'run.mf4')]) == 2
    dbc = tmp_path / 'car.dbc'
    dbc.write_text('VERSION ""\n')
    assert load_script('make_arxml').main(['--dbc', str(dbc), '--out', str(dbc)]) == 2
    err = capsys.readouterr().err
    assert err.count('a tool never writes') == 7, err
    assert {p.name: p.read_bytes() for p in bag.iterdir()} == before
    assert store.read_text() == '' and dbc.read_text() == 'VERSION ""\n'


@pytest.mark.parametrize('argv', [
    ['simulate', '--scenario', 'steady_dry', '--json', 'DIR'],
    ['campaign', '--scenario', 'steady_dry', '--store', 'DIR'],
    ['campaign', '--scenario', 'steady_dry', '--store', 'DIR/s.jsonl', '--summary', 'DIR'],
    ['results_table', '--only', 'steady_dry', '--json', 'DIR'],
    ['estimator_eval', '--synthetic', '1', '--out', 'DIR'],
])
def test_an_output_path_that_cannot_be_written_is_refused_before_the_runs(tmp_path, capsys,
                                                                          argv):
    script, *args = argv
    args = [a.replace('DIR', str(tmp_path)) for a in args]
    assert load_script(script).main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and 'is a directory' in err[0], err
    assert not any(p.suffix == '.jsonl' for p in tmp_path.iterdir())


def test_the_summary_and_its_json_may_not_be_one_file(tmp_path, capsys):
    store = tmp_path / 's.jsonl'
    argv = ['--scenario', 'steady_dry', '--store', str(store), '--summary',
            str(tmp_path / 'a.md'), '--summary-json', str(tmp_path / 'a.md')]
    assert load_script('campaign').main(argv) == 2
    assert 'name the same file' in capsys.readouterr().err
    assert not store.exists()


@pytest.mark.parametrize('argv', [
    ['topic', 'hz', '/x', '--window', '1'],             # printed "no messages" at any rate
    ['topic', 'pub', '/x', 'std_msgs/msg/Float64', '-r', 'nan'],   # hung
    ['topic', 'list', '--wait', 'nan'],                 # hung
    ['bag', 'slice', 'a', 'b', '--end', 'inf'],         # OverflowError
])
def test_the_operator_refuses_numbers_that_hang_or_crash_it(argv, capsys):
    from drift_tools.operator import parser
    with pytest.raises(SystemExit) as done:
        parser().parse_args(argv)
    assert done.value.code == 2 and 'expected' in capsys.readouterr().err


@pytest.mark.parametrize('script, argv', [
    ('replay', ['bag', '--loop', '-1']),                # looped forever
    ('replay', ['bag', '--rate', 'nan']),
    ('bench_model', ['--repeat', '0']),                 # ZeroDivisionError
    ('estimator_eval', ['--synthetic', '1', '--seeds', '-1']),
    ('estimator_eval', ['--window', '50', '20']),
])
def test_scripts_refuse_bad_numbers_before_the_work(script, argv, capsys):
    with pytest.raises(SystemExit) as done:
        load_script(script).main(argv)
    assert done.value.code == 2 and 'error' in capsys.readouterr().err
