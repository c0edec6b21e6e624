"""A node whose timer callback publishes after the context was shut down: the race of a SIGINT
arriving while a callback runs, made deterministic. ``run_node`` must end it with exit code 0.
With the argument ``fail`` the callback raises while the context is up: that must fail the run;
with ``interrupt`` it raises what a SIGINT inside a C extension becomes (an error caused by a
KeyboardInterrupt): a clean end again; with ``early`` it raises first and the context goes down
50 ms later from another thread, as rclpy's signal-handler thread does it: a clean end too;
with ``close`` its ``close()`` prints a line (not flushed) and sets exit code 3."""
import sys
import threading

import rclpy
from rclpy.node import Node
from std_msgs.msg import Empty

from drift_control.nodes.spin import run_node


class PublishAfterShutdown(Node):
    def __init__(self):
        super().__init__('publish_after_shutdown')
        self._pub = self.create_publisher(Empty, 'race', 1)
        self.create_timer(0.01, self._tick)

    def _tick(self):
        if 'fail' in sys.argv[1:]:
            raise ValueError('a real failure while running')
        if 'early' in sys.argv[1:]:
            threading.Timer(0.05, rclpy.shutdown).start()
            raise RuntimeError('Unable to convert call argument')
        if 'interrupt' in sys.argv[1:]:
            try:
                raise KeyboardInterrupt
            except KeyboardInterrupt as err:
                raise SystemError('returned a result with an exception set') from err
        rclpy.shutdown()          # what the SIGINT handler does, between two lines of a callback
        self._pub.publish(Empty())

    def close(self):
        if 'close' in sys.argv[1:]:
            print('closed: the bag is whole')   # a pipe: block-buffered, flushed by the exit
            self.exit_code = 3


if __name__ == '__main__':
    sys.exit(run_node(PublishAfterShutdown, 'publish_after_shutdown'))
