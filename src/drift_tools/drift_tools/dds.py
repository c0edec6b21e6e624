"""The DDS transport of the stack's processes: UDP, never Fast DDS's shared memory.

Fast DDS 2.14 opens a reader's shared-memory port on the first write to it, in the writer's
thread, and checks the port's listener first; a listener idle since the last watchdog check
looks frozen, and the check sleeps a third of ``healthy_check_timeout_ms`` (333 ms) before it
looks again. rclpy holds the GIL through the publish, so the whole node stops: a bridge missed
its CAN cycle, a car its step (docs/dds.md). Over UDP the write never waits on a reader.

``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` makes rmw_fastrtps add its own shared-memory transport
whatever the profile says, so LOCALHOST is carried out with ``SYSTEM_DEFAULT`` and
``config/dds/localhost_udp.xml`` (loopback only, discovery to 127.0.0.1); SUBNET and SYSTEM_DEFAULT
keep Fast DDS's discovery with ``FASTDDS_BUILTIN_TRANSPORTS=UDPv4``. A profile the user set
(``FASTRTPS_DEFAULT_PROFILES_FILE``) or another RMW is left alone.
"""
from __future__ import annotations

import os
from pathlib import Path

from drift_control.params import ParamError
from drift_control.params import config_dir as find_config_dir

PROFILE = Path('dds') / 'localhost_udp.xml'     # below the config directory
PROFILE_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'
RANGE_ENV = 'ROS_AUTOMATIC_DISCOVERY_RANGE'
FASTRTPS = 'rmw_fastrtps_cpp'


def transport_env(env: dict, discovery_range: str, config_dir: Path | None,
                  shared_memory: bool = False) -> dict:
    """``env`` with the discovery range set and, for Fast DDS, the UDP-only transport.

    ``shared_memory`` keeps rmw_fastrtps's own choice (shared memory and UDP). Returns ``env``.
    """
    env[RANGE_ENV] = discovery_range
    own_choice = (shared_memory or env.get(PROFILE_ENV) or env.get('FASTDDS_BUILTIN_TRANSPORTS')
                  or env.get('RMW_IMPLEMENTATION', FASTRTPS) != FASTRTPS)
    if own_choice or discovery_range == 'OFF':
        return env
    if discovery_range == 'LOCALHOST':
        profile = Path(config_dir) / PROFILE if config_dir is not None else None
        if profile is None or not profile.is_file():
            return env          # a config without the profile: rmw's LOCALHOST, shared memory
        env[RANGE_ENV] = 'SYSTEM_DEFAULT'
        env[PROFILE_ENV] = str(profile.resolve())
    else:
        env['FASTDDS_BUILTIN_TRANSPORTS'] = 'UDPv4'
    return env


def use_udp_here(config_dir: Path | None = None) -> None:
    """For a tool's own process, before ``rclpy.init``: the range from the environment
    (default LOCALHOST), carried out as :func:`transport_env` does for the nodes."""
    if config_dir is None:
        try:
            config_dir = find_config_dir()
        except ParamError:      # no config directory: rmw's own transports
            config_dir = None
    transport_env(os.environ, os.environ.get(RANGE_ENV) or 'LOCALHOST', config_dir)
