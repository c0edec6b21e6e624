"""QoS of the loop's outputs, one definition for every node that publishes them."""
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

KEPT_DEPTH = 100   # messages a late-matched subscription still gets: 1 s of state at 100 Hz


def kept_qos() -> QoSProfile:
    """Reliable, transient local, the last ``KEPT_DEPTH`` messages kept.

    Discovery is not symmetric: a subscription can be matched and listed while the publisher has
    not matched it yet, and Fast DDS gives a volatile reader nothing written before the match is
    complete on both sides (1 lock-step bag in 60-100 lacked its first commands). A transient-local
    subscription (the recorder's) gets the kept messages once matched; a volatile one (the
    simulator's, the bridge's) only new messages, as before.
    """
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=KEPT_DEPTH,
                      reliability=ReliabilityPolicy.RELIABLE,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL)
