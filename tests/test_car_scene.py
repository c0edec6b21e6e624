"""The car in 3D without ROS: footprint and wheel geometry, and the scene's messages as CDR."""
import math

import pytest
from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

from drift_control.params import ParamError, load_vehicle
from drift_tools.car_scene import (ARROW, DELETE, MARKERS_TOPIC, REFERENCE_TOPIC, STATE_TOPIC,
                                   TRANSFORM_TOPIC, CarPose, CarScene, CarShape, footprint,
                                   reference_point, wheels)
from drift_tools.msgdef import message_definition


def codec(msgtype, make):
    return make(msgtype, message_definition(msgtype))[msgtype]


encode_state = codec('drift_msgs/msg/VehicleState', serialize_dynamic)
encode_reference = codec('drift_msgs/msg/DriftReference', serialize_dynamic)
decode_markers = codec('visualization_msgs/msg/MarkerArray', generate_dynamic)
decode_transform = codec('geometry_msgs/msg/TransformStamped', generate_dynamic)


@pytest.fixture(scope='module')
def shape():
    return CarShape.from_vehicle(load_vehicle('gr86'), track=1.52)


def pose(**kw):
    values = dict(stamp=1.0, x=3.0, y=-2.0, yaw=0.7, V=12.0, beta=-0.5, delta=-0.15)
    values.update(kw)
    return CarPose(**values)


def state_cdr(p: CarPose, validity=2047):
    sec = math.floor(p.stamp)
    return encode_state({'header': {'stamp': {'sec': sec, 'nanosec': round((p.stamp - sec) * 1e9)}},
                         'x': p.x, 'y': p.y, 'yaw': p.yaw, 'v': p.V, 'beta': p.beta,
                         'delta': p.delta, 'validity': validity})


def reference_cdr(stamp, e_y, heading_error):
    sec = math.floor(stamp)
    return encode_reference({'header': {'stamp': {'sec': sec,
                                                  'nanosec': round((stamp - sec) * 1e9)}},
                             'e_y': e_y, 'heading_error': heading_error})


def dist(p, q):
    return math.hypot(p[0] - q[0], p[1] - q[1])


def test_the_gr86_outline_matches_its_published_size(shape):
    # 2575 mm wheelbase, 1520 mm front track; published 4265 x 1775 mm
    assert shape.front + shape.rear == pytest.approx(4.265, abs=0.1)
    assert shape.width == pytest.approx(1.775, abs=0.05)


@pytest.mark.parametrize('yaw', [0.0, 0.7, -2.5])
def test_footprint_is_a_rectangle_around_the_cog_facing_the_heading(shape, yaw):
    p = pose(yaw=yaw)
    fl, rl, rr, fr = footprint(p, shape)
    assert dist(fl, rl) == pytest.approx(shape.front + shape.rear)
    assert dist(fl, fr) == pytest.approx(shape.width)
    assert dist(fl, rr) == pytest.approx(math.hypot(shape.front + shape.rear, shape.width))
    front_mid = (0.5 * (fl[0] + fr[0]), 0.5 * (fl[1] + fr[1]))
    # the front edge's middle lies straight ahead of the CoG, a bumper's distance away
    assert front_mid[0] - p.x == pytest.approx(shape.front * math.cos(yaw))
    assert front_mid[1] - p.y == pytest.approx(shape.front * math.sin(yaw))
    # left is left: the front-left corner is on the left of the heading
    assert math.cos(yaw) * (fl[1] - p.y) - math.sin(yaw) * (fl[0] - p.x) > 0


@pytest.mark.parametrize('delta', [-0.4, 0.0, 0.25])
def test_front_wheels_turn_by_delta_and_rear_wheels_follow_the_body(shape, delta):
    w = wheels(pose(delta=delta), shape)
    assert w['FL'][2] == w['FR'][2] == pytest.approx(0.7 + delta)
    assert w['RL'][2] == w['RR'][2] == pytest.approx(0.7)
    assert dist(w['FL'], w['RL']) == pytest.approx(shape.a + shape.b)     # the wheelbase
    assert dist(w['FL'], w['FR']) == pytest.approx(shape.track)
    # the CoG sits on the axle line, b from the rear axle
    rear_mid = (0.5 * (w['RL'][0] + w['RR'][0]), 0.5 * (w['RL'][1] + w['RR'][1]))
    assert dist(rear_mid, (3.0, -2.0)) == pytest.approx(shape.b)


@pytest.mark.parametrize('e_y,heading_error', [(0.8, 0.1), (-1.5, -0.3), (0.0, 0.0)])
def test_reference_point_is_e_y_from_the_car_across_the_path(e_y, heading_error):
    p = pose()
    ref = reference_point(p, e_y, heading_error, p.stamp)
    assert dist((ref.x, ref.y), (p.x, p.y)) == pytest.approx(abs(e_y))
    tangent = (math.cos(ref.theta), math.sin(ref.theta))
    offset = (p.x - ref.x, p.y - ref.y)
    assert tangent[0] * offset[0] + tangent[1] * offset[1] == pytest.approx(0.0, abs=1e-12)
    # positive e_y: the car is left of the path
    assert tangent[0] * offset[1] - tangent[1] * offset[0] == pytest.approx(e_y)


def test_the_scene_decodes_with_the_bag_schemas_and_draws_the_state(shape):
    scene = CarScene(shape, period=0.05, arrow_time=0.25)
    p = pose()
    assert scene.offer(REFERENCE_TOPIC, reference_cdr(p.stamp, 0.6, 0.2)) == []  # no state yet
    out = dict(scene.offer(STATE_TOPIC, state_cdr(p)))
    scene.offer(REFERENCE_TOPIC, reference_cdr(p.stamp, 0.6, 0.2))
    tf = decode_transform(out[TRANSFORM_TOPIC])
    assert (tf.header.frame_id, tf.child_frame_id) == ('map', 'base_link')
    assert (tf.transform.translation.x, tf.transform.translation.y) == (p.x, p.y)
    assert 2 * math.atan2(tf.transform.rotation.z, tf.transform.rotation.w) == pytest.approx(p.yaw)
    markers = {(m.ns, m.id): m for m in decode_markers(out[MARKERS_TOPIC]).markers}
    assert markers[('reference', 0)].action == DELETE      # the reference came before its state
    velocity = markers[('velocity', 0)]
    start, end = velocity.points
    assert velocity.type == ARROW
    assert dist((start.x, start.y), (p.x, p.y)) == pytest.approx(0.0)
    assert dist((end.x, end.y), (start.x, start.y)) == pytest.approx(p.V * 0.25)
    assert math.atan2(end.y - start.y, end.x - start.x) == pytest.approx(p.yaw + p.beta)
    outline = [(q.x, q.y) for q in markers[('car', 1)].points]
    assert outline[0] == outline[-1] and len(outline) == 5
    for (x, y), q in zip(footprint(p, shape), outline):
        assert (x, y) == pytest.approx(q)
    front_left = markers[('wheels', 0)].pose.orientation
    assert 2 * math.atan2(front_left.z, front_left.w) == pytest.approx(p.yaw + p.delta)

    # the next scene, a period later, has the reference point matched to its own state
    later = dict(scene.offer(STATE_TOPIC, state_cdr(p._replace(stamp=1.05, x=3.5))))
    markers = {(m.ns, m.id): m for m in decode_markers(later[MARKERS_TOPIC]).markers}
    a, b = markers[('lateral_error', 0)].points
    assert dist((a.x, a.y), (b.x, b.y)) == pytest.approx(0.6)
    assert (b.x, b.y) == pytest.approx((p.x, p.y))         # measured from the 1.00 s state
    assert markers[('lateral_error', 1)].text == 'e_y +0.60 m'


def test_scenes_come_once_per_period_of_state_time_and_restart_with_a_new_run(shape):
    scene = CarScene(shape, period=0.05)
    stamps = [round(0.01 * k, 2) for k in range(21)]
    drawn = [t for t in stamps if scene.offer(STATE_TOPIC, state_cdr(pose(stamp=t)))]
    assert drawn == [0.0, 0.05, 0.1, 0.15, 0.2]
    assert scene.offer(STATE_TOPIC, state_cdr(pose(stamp=0.03)))    # time went back


def test_a_stale_reference_is_deleted(shape):
    scene = CarScene(shape, period=0.01, reference_timeout=0.5)
    scene.offer(STATE_TOPIC, state_cdr(pose(stamp=1.0)))
    scene.offer(REFERENCE_TOPIC, reference_cdr(1.0, 0.3, 0.0))
    fresh = dict(scene.offer(STATE_TOPIC, state_cdr(pose(stamp=1.4))))
    stale = dict(scene.offer(STATE_TOPIC, state_cdr(pose(stamp=1.6))))
    actions = [{(m.ns, m.id): m.action for m in decode_markers(out[MARKERS_TOPIC]).markers}
               for out in (fresh, stale)]
    assert actions[0][('reference', 0)] != DELETE
    assert actions[1][('reference', 0)] == DELETE


def test_bad_messages_are_counted_not_raised(shape):
    scene = CarScene(shape)
    assert scene.offer(STATE_TOPIC, b'\x00\x01\x00\x00short') == []
    assert scene.offer(STATE_TOPIC, state_cdr(pose(x=float('nan')))) == []
    assert scene.offer(STATE_TOPIC, state_cdr(pose(), validity=2047 & ~1024)) == []  # no pose
    assert scene.offer('drift/command', b'anything') == []         # not the scene's topic
    assert scene.rejected == 1 and 'vehicle/state: undecodable' in scene.last_error
    assert scene.offer(STATE_TOPIC, state_cdr(pose()))              # still drawing


def test_bad_shape_or_rates_are_one_line(shape):
    with pytest.raises(ParamError, match='track must be positive'):
        CarShape.from_vehicle(load_vehicle('gr86'), track=0.0)
    with pytest.raises(ParamError, match='period'):
        CarScene(shape, period=0.0)
