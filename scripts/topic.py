#!/usr/bin/env python3
"""Live topics from the command line: ``drift topic list|echo|hz|pub`` (drift_tools.operator).

    .venv/bin/python scripts/topic.py list -t
    .venv/bin/python scripts/topic.py echo /vehicle/state -n 1
    .venv/bin/python scripts/topic.py hz /drift/command --window 100

Uses ROS_DOMAIN_ID from the environment; ROS_AUTOMATIC_DISCOVERY_RANGE defaults to LOCALHOST.
"""
import sys

from drift_tools.operator import main

if __name__ == '__main__':
    sys.exit(main(['topic', *sys.argv[1:]]))
