"""Run metadata kept in the bag: collected before the run, read back by the tools."""
import json

from conftest import REPO
from drift_tools.bag_writer import BagWriter
from drift_tools.run_info import RECORD_NAME, collect, read_run_info, run_scenario


def test_collect_has_the_settings_config_and_version():
    info = collect(REPO / 'config', scenario='steady_wet', vehicle='gr86', seed=3,
                   overrides=['surface.mu=0.9'], graph='sim', clock='lockstep',
                   argv=['run_stack.py', '--seed', '3'])
    assert all(isinstance(v, str) for v in info.values())
    assert info['seed'] == '3' and json.loads(info['overrides']) == ['surface.mu=0.9']
    files = json.loads(info['config'])
    assert 'nmpc.yaml' in files and 'vehicle/gr86.yaml' in files and 'can/drift_vehicle.dbc' in files
    assert len(info['commit']) == 40 and info['dirty'] in ('true', 'false')
    assert info['command_line'] == 'run_stack.py --seed 3'


def test_read_back_from_a_finished_and_an_unfinished_bag(tmp_path):
    info = collect(REPO / 'config', scenario='steady_wet', vehicle='gr86', seed=None)
    w = BagWriter(tmp_path / 'live')
    w.add_metadata(RECORD_NAME, info)
    w.add_topic('/note', 'std_msgs/msg/String')
    w.write('/note', b'\x00\x01\x00\x00\x02\x00\x00\x00a\x00', 1)
    w.flush()
    assert read_run_info(tmp_path / 'live')['scenario'] == 'steady_wet'   # no summary yet
    w.close()
    back = read_run_info(tmp_path / 'live')
    assert back == info
    spec = run_scenario(back)
    assert spec.vehicle == 'gr86' and spec.surface.name == 'wet'
    assert run_scenario({'scenario': 'no_such_scenario'}) is None
    assert run_scenario(None) is None


def test_a_large_config_file_is_kept_as_its_hash(tmp_path):
    """A generated ARXML (~0.5 MB) must not fill a small disk with every bag's run record."""
    import hashlib
    from drift_tools.run_info import KEEP_BYTES, config_files
    (tmp_path / 'bridge.yaml').write_text('cycle_time: 0.01\n')
    big = b'<AUTOSAR/>' + b' ' * KEEP_BYTES
    (tmp_path / 'flexray').mkdir()
    (tmp_path / 'flexray' / 'car.arxml').write_bytes(big)
    files = config_files(tmp_path)
    assert files['bridge.yaml'] == 'cycle_time: 0.01\n'
    assert files['flexray/car.arxml'] == \
        f'sha256:{hashlib.sha256(big).hexdigest()} ({len(big)} bytes, not kept)'
