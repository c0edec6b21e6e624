"""Lock-step pacing: the simulator advances only when the controller's command has arrived.

The controller runs on sim time at ``command_period`` (the NMPC's 20 ms): at every multiple of
it, from t = 0 on, the step waits for a command stamped at or after the current sim time. A wait
longer than ``timeout`` (wall clock) advances anyway with the held command and is counted in
``timeouts`` -- reported, never silent. The first command may take ``startup_timeout``
(controllers build their solvers on start-up). The initial state waits too: stepping on without
its command made the controller's first solve the one of 0 s or of 20 ms, depending on when it
joined, and two runs of one seed differed from the third sample on.
"""
from __future__ import annotations

from drift_control.signals import Command


class LockstepGate:
    """Decides whether the simulator may take its next step.

    Parameters
    ----------
    dt : float
        Simulator step [s].
    command_period : float
        Controller period in sim time [s].
    timeout : float
        Longest wall-clock wait for a command once the controller is running [s].
    startup_timeout : float
        Longest wall-clock wait for the very first command [s].
    wait_reference : bool
        Also wait for a reference of a state after the previous command step.
    """

    def __init__(self, dt: float, command_period: float, timeout: float,
                 startup_timeout: float, wait_reference: bool = False):
        self.dt, self.timeout, self.startup_timeout = dt, timeout, startup_timeout
        self.wait_reference = wait_reference
        self.reference_stamp = -float('inf')
        self.every = max(1, int(round(command_period / dt)))
        self.command: Command | None = None
        self.timeouts = 0
        self.missed_in_row = 0     # command steps in a row that timed out
        self._wait_since: float | None = None

    def offer(self, command: Command) -> None:
        """A command arrived."""
        self.command = command

    def offer_reference(self, stamp: float) -> None:
        """A reference for the state at ``stamp`` [s] arrived."""
        self.reference_stamp = max(self.reference_stamp, stamp)

    def expects(self, t: float) -> bool:
        """A command for sim time ``t`` [s] is due before stepping on."""
        return int(round(t / self.dt)) % self.every == 0

    def ready(self, t: float, wall: float) -> bool:
        """May the simulator step from sim time ``t``? ``wall`` is a monotonic clock [s]."""
        eps = 0.5 * self.dt
        # a command for this step: stamped at it (a command stamped far ahead is no command for
        # every step to come: it would run the plant open loop)
        have = (self.command is not None
                and t - eps <= self.command.stamp <= t + self.every * self.dt + eps
                and (not self.wait_reference
                     or self.reference_stamp > t - self.every * self.dt + eps))
        if not self.expects(t) or have:
            self._wait_since = None
            self.missed_in_row = 0 if have else self.missed_in_row
            return True
        if self._wait_since is None:
            self._wait_since = wall
        limit = self.timeout if self.command is not None else self.startup_timeout
        if wall - self._wait_since > limit:
            self.timeouts += 1
            self.missed_in_row += 1
            self._wait_since = None
            return True
        return False
