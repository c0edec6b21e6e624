"""The car in 3D: footprint, wheels, velocity, reference point and lateral error as ROS messages.

Everything is drawn in the ``map`` frame as one ``visualization_msgs/MarkerArray``, with the body
pose also given as a ``geometry_msgs/TransformStamped`` (``map`` -> ``base_link``), so a viewer
needs no transform tree to show it. Messages go in and out as CDR bytes with the same ``.msg``
definitions the bags carry (``drift_tools.msgdef``), encoded and decoded by ``mcap_ros2``: no
ROS installation is needed to build or test the scene.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

from mcap_ros2._dynamic import generate_dynamic, serialize_dynamic

from drift_control.params import ParamError, VehicleParams
from drift_tools.msgdef import message_definition

MAP_FRAME, BODY_FRAME = 'map', 'base_link'
STATE_TOPIC, REFERENCE_TOPIC = 'vehicle/state', 'drift/reference'
MARKERS_TOPIC, TRANSFORM_TOPIC = 'drift/view/markers', 'drift/view/tf'
# what the scene publishes (relative names, as the stack's topics) -> message type
VIEW_TOPICS = {
    MARKERS_TOPIC: 'visualization_msgs/msg/MarkerArray',
    TRANSFORM_TOPIC: 'geometry_msgs/msg/TransformStamped',
}
VALID_POSE = 1024          # drift_msgs/VehicleState.VALID_POSE
ARROW, CUBE, SPHERE, LINE_STRIP, LINE_LIST, TEXT = 0, 1, 2, 4, 5, 9   # Marker.type
ADD, DELETE = 0, 2                                                    # Marker.action


@dataclass(frozen=True)
class CarShape:
    """The car's outline for drawing, in the body frame (x forward, y left, origin at the CoG).

    The single-track model knows the axles (``a``, ``b``) and the wheel radii; the track comes
    from elsewhere (a node parameter). Overhangs are a third of the wheelbase at each end (both
    cars of ``config/vehicle`` within 0.1 m of their published lengths).
    """

    a: float                 # CoG to front axle [m]
    b: float                 # CoG to rear axle [m]
    track: float             # distance between the left and right wheel centres [m]
    R_F: float               # front wheel radius [m]
    R_R: float               # rear wheel radius [m]
    wheel_width: float = 0.25    # tyre width [m]
    height: float = 0.7          # body box height drawn above the wheel centres [m]

    def __post_init__(self):
        for name in ('a', 'b', 'track', 'R_F', 'R_R', 'wheel_width', 'height'):
            if not getattr(self, name) > 0:
                raise ParamError(f'car shape: {name} must be positive, got {getattr(self, name)}')

    @classmethod
    def from_vehicle(cls, p: VehicleParams, track: float) -> CarShape:
        """The shape of a controller vehicle with a given ``track`` [m]."""
        return cls(a=p.a, b=p.b, track=track, R_F=p.R_F, R_R=p.R_R)

    @property
    def front(self) -> float:
        """Front bumper ahead of the CoG [m]."""
        return self.a + (self.a + self.b) / 3.0

    @property
    def rear(self) -> float:
        """Rear bumper behind the CoG [m]."""
        return self.b + (self.a + self.b) / 3.0

    @property
    def width(self) -> float:
        """Body width: the track plus one tyre [m]."""
        return self.track + self.wheel_width


class CarPose(NamedTuple):
    """What the scene needs of one vehicle state (SI units, radians, map frame)."""

    stamp: float      # header stamp [s]
    x: float          # CoG position [m]
    y: float
    yaw: float        # heading [rad]
    V: float          # speed over ground [m/s]
    beta: float       # sideslip [rad]
    delta: float      # road-wheel steering angle [rad]


class ReferencePoint(NamedTuple):
    """The path point a reference was selected for, and the car position it was measured from."""

    stamp: float      # the reference's header stamp [s]
    x: float          # point on the path [m]
    y: float
    theta: float      # path tangent angle there [rad]
    e_y: float        # lateral error, positive left of the path [m]
    car_x: float      # the car's CoG when the error was measured [m]
    car_y: float


def body_to_map(pose: CarPose, px: float, py: float) -> tuple[float, float]:
    """A body-frame point [m] in the map frame [m]."""
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    return pose.x + c * px - s * py, pose.y + s * px + c * py


def footprint(pose: CarPose, shape: CarShape) -> list[tuple[float, float]]:
    """The body outline in the map frame: front left, rear left, rear right, front right [m]."""
    half = 0.5 * shape.width
    corners = ((shape.front, half), (-shape.rear, half), (-shape.rear, -half),
               (shape.front, -half))
    return [body_to_map(pose, px, py) for px, py in corners]


def wheels(pose: CarPose, shape: CarShape) -> dict[str, tuple[float, float, float]]:
    """Each wheel's centre [m] and heading [rad] in the map frame; the fronts turned by delta."""
    half = 0.5 * shape.track
    centres = {'FL': (shape.a, half), 'FR': (shape.a, -half),
               'RL': (-shape.b, half), 'RR': (-shape.b, -half)}
    out = {}
    for name, (px, py) in centres.items():
        heading = pose.yaw + (pose.delta if name[0] == 'F' else 0.0)
        out[name] = (*body_to_map(pose, px, py), heading)
    return out


def reference_point(pose: CarPose, e_y: float, heading_error: float,
                    stamp: float) -> ReferencePoint:
    """The path point a reference's lateral error is measured from.

    Frenet coordinates place the car ``e_y`` along the path's left normal from that point, and
    the path's tangent is the car's yaw minus ``heading_error`` (``drift_msgs/DriftReference``).
    """
    theta = pose.yaw - heading_error
    return ReferencePoint(stamp, pose.x + e_y * math.sin(theta), pose.y - e_y * math.cos(theta),
                          theta, e_y, pose.x, pose.y)


def _point(x, y, z=0.0) -> dict:
    return {'x': x, 'y': y, 'z': z}


def _yaw_quaternion(yaw: float) -> dict:
    return {'x': 0.0, 'y': 0.0, 'z': math.sin(0.5 * yaw), 'w': math.cos(0.5 * yaw)}


def _color(r, g, b, a=1.0) -> dict:
    return {'r': r, 'g': g, 'b': b, 'a': a}


def _marker(header, ns, mid, kind, *, color, scale=(1.0, 1.0, 1.0), at=(0.0, 0.0, 0.0),
            yaw=0.0, points=(), text='') -> dict:
    return {'header': header, 'ns': ns, 'id': mid, 'type': kind, 'action': ADD,
            'pose': {'position': _point(*at), 'orientation': _yaw_quaternion(yaw)},
            'scale': _point(*scale), 'color': color, 'points': list(points), 'text': text}


def _arrow(header, ns, mid, start, end, z, color, shaft=0.12) -> dict:
    return _marker(header, ns, mid, ARROW, color=color, scale=(shaft, 2.5 * shaft, 3.0 * shaft),
                   points=(_point(*start, z), _point(*end, z)))


def car_markers(pose: CarPose, shape: CarShape, header: dict, arrow_time: float) -> list[dict]:
    """Body, outline, wheels, steering and velocity arrows and a label for one pose.

    The velocity arrow points along the course (yaw + beta) and is as long as the distance the
    car covers in ``arrow_time`` [s].
    """
    outline = footprint(pose, shape)
    cx, cy = body_to_map(pose, 0.5 * (shape.front - shape.rear), 0.0)
    z_body = max(shape.R_F, shape.R_R) + 0.5 * shape.height
    markers = [
        _marker(header, 'car', 0, CUBE, color=_color(0.3, 0.6, 1.0, 0.35), at=(cx, cy, z_body),
                yaw=pose.yaw, scale=(shape.front + shape.rear, shape.width, shape.height)),
        _marker(header, 'car', 1, LINE_STRIP, color=_color(1.0, 1.0, 1.0), scale=(0.06, 0, 0),
                points=[_point(x, y, 0.02) for x, y in outline + outline[:1]]),
    ]
    for i, (name, (x, y, heading)) in enumerate(wheels(pose, shape).items()):
        radius = shape.R_F if name[0] == 'F' else shape.R_R
        color = _color(1.0, 0.55, 0.0) if name[0] == 'F' else _color(0.15, 0.15, 0.15)
        markers.append(_marker(header, 'wheels', i, CUBE, color=color, at=(x, y, radius),
                               yaw=heading, scale=(2 * radius, shape.wheel_width, 2 * radius)))
    front = body_to_map(pose, shape.a, 0.0)
    steer = pose.yaw + pose.delta
    markers.append(_arrow(header, 'steering', 0, front,
                          (front[0] + 1.5 * math.cos(steer), front[1] + 1.5 * math.sin(steer)),
                          shape.R_F, _color(1.0, 0.55, 0.0), shaft=0.08))
    course, length = pose.yaw + pose.beta, pose.V * arrow_time
    markers.append(_arrow(header, 'velocity', 0, (pose.x, pose.y),
                          (pose.x + length * math.cos(course), pose.y + length * math.sin(course)),
                          z_body + 0.5 * shape.height + 0.1, _color(0.1, 0.9, 0.2)))
    label = (f'V {pose.V:.1f} m/s  beta {math.degrees(pose.beta):.1f} deg  '
             f'delta {math.degrees(pose.delta):.1f} deg')
    markers.append(_marker(header, 'label', 0, TEXT, color=_color(1.0, 1.0, 1.0),
                           at=(pose.x, pose.y, z_body + shape.height + 1.0), scale=(0, 0, 0.5),
                           text=label))
    return markers


def reference_markers(ref: ReferencePoint | None, header: dict) -> list[dict]:
    """The reference point, the path's direction there and the lateral error line and label.

    ``None`` deletes them (no reference, or one too old for the current state).
    """
    if ref is None:
        return [{'header': header, 'ns': ns, 'id': mid, 'action': DELETE}
                for ns, mid in (('reference', 0), ('reference', 1), ('lateral_error', 0),
                                ('lateral_error', 1))]
    magenta, yellow = _color(1.0, 0.2, 0.9), _color(1.0, 0.9, 0.1)
    tip = (ref.x + 1.5 * math.cos(ref.theta), ref.y + 1.5 * math.sin(ref.theta))
    return [
        _marker(header, 'reference', 0, SPHERE, color=magenta, at=(ref.x, ref.y, 0.25),
                scale=(0.5, 0.5, 0.5)),
        _arrow(header, 'reference', 1, (ref.x, ref.y), tip, 0.25, magenta, shaft=0.08),
        _marker(header, 'lateral_error', 0, LINE_LIST, color=yellow, scale=(0.08, 0, 0),
                points=(_point(ref.x, ref.y, 0.25), _point(ref.car_x, ref.car_y, 0.25))),
        _marker(header, 'lateral_error', 1, TEXT, color=yellow, scale=(0, 0, 0.45),
                at=(0.5 * (ref.x + ref.car_x), 0.5 * (ref.y + ref.car_y), 0.8),
                text=f'e_y {ref.e_y:+.2f} m'),
    ]


def body_transform(pose: CarPose, header: dict) -> dict:
    """``map`` -> ``base_link`` at the CoG, as a ``geometry_msgs/TransformStamped`` mapping."""
    return {'header': header, 'child_frame_id': BODY_FRAME,
            'transform': {'translation': _point(pose.x, pose.y),
                          'rotation': _yaw_quaternion(pose.yaw)}}


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def pose_from_state(msg) -> CarPose | None:
    """A decoded ``VehicleState`` as a pose; None without a valid, finite pose (or with a stamp
    before time 0, which a header cannot carry)."""
    if not msg.validity & VALID_POSE:
        return None
    pose = CarPose(_stamp(msg), msg.x, msg.y, msg.yaw, msg.v, msg.beta, msg.delta)
    return pose if pose.stamp >= 0 and all(math.isfinite(v) for v in pose) else None


class CarScene:
    """Turns vehicle states and references (CDR) into the scene's messages (CDR).

    Parameters
    ----------
    shape : CarShape
        The car to draw.
    period : float
        Least state time between two scenes [s]; states in between only update the pose a
        reference is matched with.
    arrow_time : float
        The velocity arrow's length as travel time [s].
    reference_timeout : float
        A reference further than this from the state's stamp is not drawn [s].
    """

    def __init__(self, shape: CarShape, period: float = 0.05, arrow_time: float = 0.25,
                 reference_timeout: float = 0.5):
        if not (period > 0 and arrow_time > 0 and reference_timeout > 0):
            raise ParamError('car scene: period, arrow_time and reference_timeout must be > 0')
        self.shape, self.period = shape, period
        self.arrow_time, self.reference_timeout = arrow_time, reference_timeout
        self._decode = {topic: _codec(msgtype, generate_dynamic) for topic, msgtype in (
            (STATE_TOPIC, 'drift_msgs/msg/VehicleState'),
            (REFERENCE_TOPIC, 'drift_msgs/msg/DriftReference'))}
        self._encode = {topic: _codec(t, serialize_dynamic) for topic, t in VIEW_TOPICS.items()}
        self._poses = deque(maxlen=64)   # recent poses: a reference is drawn from its own state's
        self._reference = None
        self._last_scene = None          # stamp of the last scene [s]
        self.rejected = 0                # messages that did not decode or made no sense
        self.last_error = ''

    def offer(self, topic: str, data: bytes) -> list[tuple[str, bytes]]:
        """Take one message of ``topic`` (relative name); returns ``(topic, cdr)`` to publish."""
        decode = self._decode.get(topic)
        if decode is None:
            return []
        try:
            msg = decode(data)
        except Exception as err:   # a broken payload fails in many ways; none may stop a node
            self.rejected += 1
            self.last_error = f'{topic}: undecodable ({type(err).__name__}: {err})'
            return []
        if topic == REFERENCE_TOPIC:
            self._on_reference(msg)
            return []
        pose = pose_from_state(msg)
        if pose is None:
            return []
        return self._on_pose(pose)

    def _on_reference(self, msg) -> None:
        stamp = _stamp(msg)
        if not self._poses or not all(map(math.isfinite, (stamp, msg.e_y, msg.heading_error))):
            return
        pose = next((p for p in reversed(self._poses) if abs(p.stamp - stamp) < 1e-6),
                    self._poses[-1])
        self._reference = reference_point(pose, msg.e_y, msg.heading_error, stamp)

    def _on_pose(self, pose: CarPose) -> list[tuple[str, bytes]]:
        last = self._last_scene
        if self._poses and pose.stamp < self._poses[-1].stamp:
            self._poses.clear()              # time went back: a new run
            self._reference = last = None
        self._poses.append(pose)
        if last is not None and pose.stamp - last < self.period - 1e-6:
            return []
        self._last_scene = pose.stamp
        ref = self._reference
        if ref is not None and abs(pose.stamp - ref.stamp) > self.reference_timeout:
            ref = None
        sec = math.floor(pose.stamp)
        header = {'stamp': {'sec': sec, 'nanosec': min(int(round((pose.stamp - sec) * 1e9)),
                                                      999_999_999)},
                  'frame_id': MAP_FRAME}
        markers = car_markers(pose, self.shape, header, self.arrow_time)
        markers += reference_markers(ref, header)
        return [(TRANSFORM_TOPIC, self._encode[TRANSFORM_TOPIC](body_transform(pose, header))),
                (MARKERS_TOPIC, self._encode[MARKERS_TOPIC]({'markers': markers}))]


def _codec(msgtype: str, make):
    """The mcap_ros2 decoder or encoder of ``msgtype`` built from its bag schema."""
    return make(msgtype, message_definition(msgtype))[msgtype]
