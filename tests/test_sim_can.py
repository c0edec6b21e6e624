"""CAN vehicle mode: the simulator behind the car's end of the DBC, the bridge's gateway in front."""
import can
import pytest

from drift_control.signals import Command, Mode

pytest.importorskip('drift_vehicle_bridge.vehicle_side')

from drift_sim.can_vehicle import CanVehicle  # noqa: E402
from drift_sim.scenario import load_scenario  # noqa: E402
from drift_sim.simulator import Simulator  # noqa: E402
from drift_vehicle_bridge.gateway import Gateway  # noqa: E402
from drift_vehicle_bridge.params import load_bridge_params  # noqa: E402
from drift_vehicle_bridge.vehicle_side import CarSide  # noqa: E402

STRAIGHT = ('path={type: segments, segments: [{length: 300.0, curvature: 0.0}]}',
            'initial.yaw_rate_from_path=false', 'duration=5.0')


def test_bridge_gateway_drives_the_simulated_car_over_a_virtual_bus():
    with can.Bus('sim_can_test', interface='virtual') as car_bus, \
            can.Bus('sim_can_test', interface='virtual') as our_bus:
        car = CarSide(car_bus)
        gateway = Gateway(our_bus, car.codec, load_bridge_params())
        sim = Simulator(load_scenario('steady_dry', STRAIGHT))
        vehicle = CanVehicle(sim, car)
        torque_when_armed = None
        for k in range(150):
            now = 0.01 * k
            vehicle.step(now)
            seen = gateway.step(now)
            if k == 20:
                assert gateway.request_arm(now)[0], 'a straight, hands-off car can be armed'
                torque_when_armed = sim.truth.state.drive_torque
            if k > 20:
                gateway.set_command(Command(now, 0.0, 0.0, 1500.0, Mode.FULL), now)
        assert torque_when_armed == pytest.approx(0.0, abs=1e-6), 'released: no drive torque'
        assert gateway.mode.name == 'ACTIVE_FULL'
        assert vehicle.command.drive_torque == pytest.approx(1500.0, abs=1.0)
        assert sim.truth.state.drive_torque > 1400.0, 'the request reached the powertrain'
        assert seen.V == pytest.approx(sim.truth.state.V, abs=0.3), 'state frames reach the bridge'
        assert vehicle.released > 20
