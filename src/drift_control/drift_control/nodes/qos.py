"""Quality of service of the loop's topics."""
from __future__ import annotations

import math

from rclpy.qos import QoSProfile, ReliabilityPolicy

HISTORY_S = 1.0   # a reliable writer keeps this much of its topic for slow readers [s]


def loop_writer_qos(rate_hz: float) -> QoSProfile:
    """Reliable, keeping ``HISTORY_S`` of samples at ``rate_hz``.

    A reliable writer whose history is full of samples some reader has not acknowledged blocks
    the publish until one is (Fast DDS, up to its max_blocking_time). With 10 samples (0.1 s at
    100 Hz) a reader slow to acknowledge while it starts, the recorder at normal priority, can
    hold a 10 ms cycle; the NMPC's command writer kept only one.
    """
    return QoSProfile(depth=max(1, math.ceil(rate_hz * HISTORY_S)),
                      reliability=ReliabilityPolicy.RELIABLE)
