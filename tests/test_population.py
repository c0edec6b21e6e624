"""Randomized plant populations: the files of both cars, their checks, and reproducible draws."""
import pytest

from drift_control.params import ParamError, vehicle_names
from drift_sim.population import draw, load_population
from drift_sim.scenario import load_scenario
from drift_sim.sensors import load_sensor_params

# the issue's ranges, the same for every car: (kind, low, high) per parameter
ISSUE_RANGES = {
    'mass': ('relative', -0.10, 0.10), 'yaw_inertia': ('relative', -0.15, 0.15),
    'cog_position': ('offset', -0.05, 0.05), 'cog_height': ('offset', -0.05, 0.05),
    'front_tyre_peak': ('relative', -0.10, 0.10), 'rear_tyre_peak': ('relative', -0.10, 0.10),
    'front_tyre_stiffness': ('relative', -0.10, 0.10),
    'rear_tyre_stiffness': ('relative', -0.10, 0.10),
    'road_friction': ('relative', -0.10, 0.10),
    'torque_lag': ('offset', 0.0, 0.04), 'torque_delay': ('offset', 0.0, 0.04),
}


@pytest.mark.parametrize('vehicle', vehicle_names())
def test_every_car_has_the_issues_ranges_each_with_its_reason(vehicle):
    population = load_population(vehicle)
    ranges = {r.name: r for r in population.ranges}
    for name, (kind, low, high) in ISSUE_RANGES.items():
        assert (ranges[name].kind, ranges[name].low, ranges[name].high) == (kind, low, high), name
    assert {'steering_bandwidth', 'steering_rate', 'lsd_locking', 'sensor_noise'} <= set(ranges)
    assert all(r.why for r in population.ranges)
    assert 'sensor_bias' in population.not_modelled   # no plant key: said, not faked
    assert ranges['road_friction'].keys == ('surface.mu',)
    assert len(ranges['sensor_noise'].keys) == 13      # every measured signal's std


def test_a_draw_is_the_same_whichever_order_draws_are_made():
    population = load_population('m3_competition')
    first = draw(population, 5, seed=0)
    draw(population, 3, seed=0)
    assert draw(population, 5, seed=0) == first
    assert draw(population, 6, seed=0) != first
    assert draw(population, 5, seed=1) != first


def test_relative_and_offset_draws_move_the_nominal_plant_within_their_ranges():
    population = load_population('gr86', scenario='steady_wet')
    nominal = population.nominal
    assert nominal['surface.mu'] == 0.6                  # the scenario's surface, wet
    for index in range(40):
        plant = draw(population, index)
        got = dict(item.split('=') for item in plant.overrides)
        for r in population.ranges:
            assert r.low <= plant.values[r.name] <= r.high, r.name
        u = plant.values
        assert float(got['plant.body.m']) == pytest.approx(
            nominal['plant.body.m'] * (1 + u['mass']), rel=1e-5)
        assert float(got['plant.body.a']) == pytest.approx(
            nominal['plant.body.a'] + u['cog_position'], rel=1e-5)
        assert float(got['surface.mu']) == pytest.approx(0.6 * (1 + u['road_friction']),
                                                         rel=1e-5)
        # one factor for the tyre's peak at every load: pDy1 and pDy2 move together
        for key in ('plant.rear_tyre.pDy1', 'plant.rear_tyre.pDy2'):
            assert float(got[key]) == pytest.approx(nominal[key] * (1 + u['rear_tyre_peak']),
                                                    rel=1e-5)


def test_the_scenario_and_the_campaigns_overrides_are_the_nominal():
    population = load_population('m3_competition', 'eps_limited_dry', ['plant.body.m=2000'])
    assert population.nominal['plant.body.m'] == 2000.0
    plant = draw(population, 0)
    mass = float(dict(o.split('=') for o in plant.overrides)['plant.body.m'])
    assert mass == pytest.approx(2000.0 * (1 + plant.values['mass']), rel=1e-5)


def test_a_draw_is_a_plant_the_simulator_accepts():
    population = load_population('gr86', 'steady_dry')
    plant = draw(population, 11, seed=3)
    loaded = load_scenario('steady_dry', plant.overrides, vehicle='gr86')
    got = dict(o.split('=') for o in plant.overrides)
    assert loaded.plant.body.m == pytest.approx(float(got['plant.body.m']))
    assert loaded.plant.lsd.locking == pytest.approx(plant.values['lsd_locking'])
    assert loaded.mu == pytest.approx(float(got['surface.mu']))


def test_the_noise_draw_reaches_the_sensor_units_only_in_runs_that_have_them():
    plain = draw(load_population('gr86', 'steady_dry'), 4, seed=1)
    sensed = draw(load_population('gr86', 'steady_dry', sensors='realistic'), 4, seed=1)
    assert sensed.overrides == plain.overrides and sensed.values == plain.values
    assert plain.sensor_set == ()
    factor = 1.0 + sensed.values['sensor_noise']
    nominal = load_sensor_params('realistic')
    got = dict(item.split('=') for item in sensed.sensor_set)
    assert float(got['ins.channels.beta.std']) == pytest.approx(
        factor * nominal.ins.channels['beta'].std, rel=1e-5)
    assert float(got['wheels.channels.RL.std']) == pytest.approx(
        factor * nominal.wheels.channels['RL'].std, rel=1e-5)
    assert not any('gm_std' in k or 'bias' in k for k in got)   # the white noise only
    drawn = load_sensor_params('realistic', overrides=sensed.sensor_set)
    assert drawn.imu.channels['r'].std == pytest.approx(factor * nominal.imu.channels['r'].std,
                                                        rel=1e-5)


BAD = [
    ('parameters: {mass: {keys: [plant.body.m], relative: [-0.1, 0.1]}}',
     'parameters.mass.why'),
    ('parameters: {mass: {keys: [plant.body.m], relative: [-0.1, 0.1], offset: [0, 1], '
     'why: x}}', 'exactly one of'),
    ('parameters: {mass: {keys: [plant.body.mass], relative: [-0.1, 0.1], why: x}}',
     'plant.body.mass names no number'),
    ('parameters: {mass: {keys: [vehicle.m], relative: [-0.1, 0.1], why: x}}',
     'only plant.* and sensors.* keys'),
    ('parameters: {noise: {keys: [sensors.ins.channels.speed.std], relative: [0, 1], why: x}}',
     'sensors.ins.channels.speed.std names no number of the sensor units'),
    ('parameters: {noise: {keys: [sensors.ins.channels.V.std], offset: [-1, 0], why: x}}',
     'parameters.noise at u = -1: sensors.ins.channels.V: std must be >= 0'),
    ('parameters: {lsd: {keys: [plant.lsd.locking], absolute: [0.5, 1.5], why: x}}',
     'parameters.lsd at u = 1.5: plant.lsd.locking'),
    ('parameters: {mass: {keys: [plant.body.m], relative: [-1.0, 0.1], why: x}}', 'above -1'),
    ('parameters: {mass: {keys: [plant.body.m], relative: [0.2, 0.1], why: x}}',
     'low <= high'),
    ('parameters: {mass: {keys: [plant.body.m], relative: [-0.1, 0.1], why: x, dist: x}}',
     "unknown key(s) ['dist']"),
    ('parameters: {a: {keys: [plant.body.m], relative: [0, 0.1], why: x},\n'
     '             b: {keys: [plant.body.m], offset: [0, 1], why: x}}', 'drawn by a'),
    ('parameters: {}\nranges: {}', "unknown key(s) ['ranges']"),
    ('parameters: []', 'parameters: expected a mapping'),
    ('- mass', 'expected a mapping at the top level'),
    ('parameters: {mass: [0.1]}', 'parameters.mass: expected a mapping'),
]


@pytest.mark.parametrize('text, message', BAD, ids=[m for _, m in BAD])
def test_a_malformed_population_file_is_one_error_naming_the_key(tmp_path, text, message):
    file = tmp_path / 'bad.yaml'
    file.write_text(text + '\n')
    with pytest.raises(ParamError, match='bad.yaml') as err:
        load_population('m3_competition', file=file)
    assert message in str(err.value)


def test_a_car_without_a_population_is_named(tmp_path):
    with pytest.raises(ParamError, match='no plant population'):
        load_population('m3_competition', file=tmp_path / 'none.yaml')
