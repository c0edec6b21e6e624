"""Where a campaign's runs execute: in this process, or as Ray tasks on this machine or a cluster.

Every executor takes a function and its items and yields ``(item, result)`` as each call
finishes, in finishing order; ``result`` is what the function returned or the exception that
ended the call, so one broken run never loses the others.

    with make_executor(workers=2) as pool:             # Ray on this machine, 2 processes
        for job, row in pool.map_unordered(run_job, jobs):
            ...
"""
from __future__ import annotations

import contextlib
import logging
import os
import socket
import sys
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Callable, Iterable, Iterator

OBJECT_STORE_BYTES = 200 * 1024 ** 2   # results are small dicts: Ray's default takes 30 % of RAM
CONNECT_TIMEOUT_S = 5.0


class ClusterError(RuntimeError):
    """Ray is missing, or the cluster at ``--address`` cannot be reached or joined."""


class Executor(ABC):
    """Runs calls of one function; a context manager that releases its workers on exit."""

    workers: int = 1

    @abstractmethod
    def map_unordered(self, fn: Callable, items: Iterable) -> Iterator[tuple]:
        """Yield ``(item, fn(item) or the exception it raised)`` as each call finishes."""

    def close(self) -> None:
        """Release the workers (a no-op for the local executor)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_interrupted = False


def interrupt(signum=None, frame=None):
    """Signal handler (SIGINT, SIGTERM): raise KeyboardInterrupt, and remember it.

    A run in this process may be inside CasADi when the signal comes: CasADi turns the
    KeyboardInterrupt into an error of that call, which the run would report as its result.
    The local executor looks at the flag after each call instead.
    """
    global _interrupted
    _interrupted = True
    raise KeyboardInterrupt


class LocalExecutor(Executor):
    """One call after the other in this process: no start-up cost, a debugger works."""

    def map_unordered(self, fn, items):
        for item in items:
            try:
                result = fn(item)
            except Exception as err:   # noqa: BLE001 - reported as that item's result
                result = err
            if _interrupted:           # the call's result may be the interrupt itself
                raise KeyboardInterrupt
            yield item, result


class RayExecutor(Executor):
    """One Ray task per call, on a local Ray instance or on the cluster at ``address``.

    Parameters
    ----------
    workers : int
        CPUs of the local instance (one task each); ignored on a cluster, which has its own.
    address : str, optional
        ``host:port`` of a cluster's head (``ray start --head``), ``ray://host:port`` for Ray
        client, or ``auto`` for a cluster started on this machine; None: a new local instance.
    """

    def __init__(self, workers: int = 2, address: str | None = None):
        if address:
            check_address(address)
            _token_auth_if_token_here()   # before Ray's import, which reads the mode
        try:
            import ray
        except ImportError:
            raise ClusterError('ray is not installed (scripts/setup.sh installs the pinned '
                               'version)') from None
        self._ray = ray
        options = dict(include_dashboard=False, logging_level=logging.ERROR,
                       log_to_driver=False)
        if address:
            options['address'] = address
        else:   # 'local': a fresh instance even when a cluster runs on this machine
            options.update(address='local', num_cpus=workers,
                           object_store_memory=OBJECT_STORE_BYTES)
        try:
            with _stderr_dropped(bool(address)):   # Ray's core retries noisily for ~20 s
                ray.init(**options)
        except Exception as err:   # noqa: BLE001 - ConnectionError, AuthenticationError, ...
            hint = (' (a cluster with token authentication needs its token here: '
                    '~/.ray/auth_token or RAY_AUTH_TOKEN; see docs/campaigns.md)' if address
                    else '')
            first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
            raise ClusterError(f'ray {address or "local"}: {first}{hint}') from None
        self.workers = int(ray.cluster_resources().get('CPU', workers))

    def map_unordered(self, fn, items):
        ray = self._ray
        remote = ray.remote(num_cpus=1)(fn)
        pending = {remote.remote(item): item for item in items}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    item = pending.pop(ref)
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayError as err:   # the worker died, a task failed
                        # a task's own exception as itself (its message, not Ray's wrapper)
                        result = getattr(err, 'cause', None) or err
                    yield item, result
        finally:   # interrupted: nothing left running on the cluster
            for ref in pending:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        self._ray.shutdown()


def make_executor(workers: int = 2, address: str | None = None) -> Executor:
    """Ray for more than one worker or a cluster; otherwise this process."""
    if workers < 1:
        raise ValueError(f'workers: expected >= 1, got {workers}')
    if address or workers > 1:
        return RayExecutor(workers, address)
    return LocalExecutor()


def check_address(address: str) -> None:
    """Refuse an address nothing listens on at once: Ray itself retries for minutes."""
    if address == 'auto':
        return
    host, sep, port = address.split('://', 1)[-1].rpartition(':')
    if not sep or not host or not port.isdigit():
        raise ClusterError(f'--address {address}: expected host:port, ray://host:port or auto')
    try:
        socket.create_connection((host, int(port)), CONNECT_TIMEOUT_S).close()
    except OSError as err:
        raise ClusterError(f'--address {address}: cannot reach it '
                           f'({err.strerror or type(err).__name__})') from None


@contextlib.contextmanager
def _stderr_dropped(drop: bool):
    """File descriptor 2 to /dev/null inside (C++ logs too), when ``drop``."""
    if not drop:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, 'w') as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _token_auth_if_token_here() -> None:
    """Send a token when one is here: ``ray start --head`` turns token authentication on
    whenever it finds one, but Ray's client never does for an explicit address. Ray reads the
    mode when it is first imported: a process that imported it before keeps its mode."""
    if 'RAY_AUTH_MODE' in os.environ:
        return
    if (os.environ.get('RAY_AUTH_TOKEN') or os.environ.get('RAY_AUTH_TOKEN_PATH')
            or (Path.home() / '.ray' / 'auth_token').is_file()):
        os.environ['RAY_AUTH_MODE'] = 'token'


__all__ = ['ClusterError', 'Executor', 'LocalExecutor', 'RayExecutor', 'check_address',
           'make_executor']
