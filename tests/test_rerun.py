"""Re-running the controller on a recorded run reproduces the recorded commands."""
import math
import shutil

import numpy as np
import pytest

ser = pytest.importorskip('rclpy.serialization')
convert = pytest.importorskip('drift_control.nodes.convert')

from drift_control.equilibrium import solve_equilibrium  # noqa: E402
from drift_control.model_plant import ModelPlant  # noqa: E402
from drift_control.nmpc import Nmpc  # noqa: E402
from drift_control.ocp import load_nmpc_params  # noqa: E402
from drift_control.params import load_vehicle  # noqa: E402
from drift_control.signals import Direction, Reference  # noqa: E402
from drift_control.vehicle import NX, X  # noqa: E402
from drift_msgs.msg import SensorSamples  # noqa: E402
from drift_tools.bag_writer import BagWriter  # noqa: E402
from drift_tools.rerun import rerun_controller  # noqa: E402


@pytest.fixture(scope='module')
def recorded(tmp_path_factory):
    vp, params = load_vehicle(), load_nmpc_params()
    eq = solve_equilibrium(math.radians(-30.0), 15.0, vp).eq
    plant = ModelPlant(vp, mu=0.95, noise={'beta': 0.002, 'r': 0.003}, seed=3)
    x0 = np.zeros(NX)
    x0[[X.V, X.BETA, X.R, X.OMEGA_F, X.OMEGA_R, X.DELTA]] = (
        eq.V, eq.beta + 0.05, eq.r, eq.omega_F, eq.omega_R, eq.delta)
    state = plant.reset(x0, t=50.0)
    live = Nmpc(vp, params)
    bag_dir = tmp_path_factory.mktemp('rerun') / 'bag'
    commands = []
    # the same run again with one raw sensor sample (an estimator's run)
    with BagWriter(bag_dir) as bag, BagWriter(bag_dir.parent / 'with_sensors') as sensed:
        for topic, typ in (('/vehicle/state', 'VehicleState'), ('/drift/reference', 'DriftReference'),
                           ('/drift/command', 'DriftCommand')):
            bag.add_topic(topic, f'drift_msgs/msg/{typ}')
            sensed.add_topic(topic, f'drift_msgs/msg/{typ}')
        sensed.add_topic('/vehicle/sensors', 'drift_msgs/msg/SensorSamples')
        sensed.write('/vehicle/sensors', ser.serialize_message(SensorSamples()),
                     int(round(state.stamp * 1e9)))
        for _ in range(40):
            ref = Reference(stamp=state.stamp, target=eq, direction=Direction.LEFT)
            t_ns = int(round(state.stamp * 1e9))
            result = live.step(state, ref, state.stamp)
            commands.append(result.command)
            for out in (bag, sensed):
                out.write('/vehicle/state', ser.serialize_message(convert.state_to_msg(state)),
                          t_ns)
                out.write('/drift/reference',
                          ser.serialize_message(convert.reference_to_msg(ref)), t_ns)
                out.write('/drift/command', ser.serialize_message(
                    convert.command_to_msg(result.command, state.stamp)), t_ns + 1)
            state = plant.step(result.command, params.Ts)
    return bag_dir, vp, params, commands


def test_rerun_with_the_same_controller_reproduces_every_command(recorded):
    bag_dir, vp, params, commands = recorded
    result = rerun_controller(bag_dir, nmpc=Nmpc(vp, params))
    assert result.commands == len(commands) and result.skipped == 0
    assert result.delta_max_deg < 1e-6 and result.torque_max_nm < 1e-3
    assert result.mode_mismatches == 0 and result.recomputed_not_ok == 0


def test_rerun_shows_a_changed_controller(recorded):
    bag_dir, vp, params, _ = recorded
    result = rerun_controller(bag_dir, nmpc=Nmpc(vp, params, mu=0.6))   # assumes a wet road
    assert result.torque_rms_nm > 50.0


def test_a_bag_without_commands_is_refused(tmp_path):
    with BagWriter(tmp_path / 'bag') as bag:
        bag.add_topic('/vehicle/state', 'drift_msgs/msg/VehicleState')
    with pytest.raises(ValueError, match='nothing recorded'):
        rerun_controller(tmp_path / 'bag')



@pytest.mark.parametrize('bag', ['bag', 'with_sensors', 'with_sensors, no metadata'])
def test_an_estimators_states_are_rerun_as_stamped(recorded, monkeypatch, tmp_path, bag):
    """A bag with the raw sensor samples holds the estimator's states, which are what their
    stamps say: the re-run's NMPC does not move them on by ``nmpc.state_age``. The metadata
    tells; without it (a salvaged bag) the messages."""
    import drift_tools.rerun as rerun
    bag_dir, vp, params, commands = recorded
    path = bag_dir.parent / bag.split(',')[0]
    if bag.endswith('no metadata'):
        path = shutil.copytree(path, tmp_path / 'salvaged')
        (path / 'metadata.yaml').unlink()
    built = []

    def build(*args):
        built.append(args[-1])
        return Nmpc(vp, params, stamped=args[-1])
    monkeypatch.setattr(rerun, '_build_nmpc', build)
    result = rerun.rerun_controller(path)
    assert built == [bag != 'bag'] and result.commands == len(commands)
