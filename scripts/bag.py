#!/usr/bin/env python3
"""Bags from the command line: ``drift bag info|recover|slice|export`` (drift_tools.operator).

    bag.py info BAG                 topics, counts, run settings; damage, if any (exit 1)
    bag.py recover BAG OUT          a repaired copy of a damaged or unfinished bag
    bag.py slice BAG OUT --start 20 --end 30 [--topics ...]
    bag.py export BAG DIR [--topics ...]     one CSV per topic
    bag.py export BAG OUT.mf4 [--topics ...] one MDF4 file: a channel group per topic,
                                             a channel per field with its unit

The input bag is never written.
"""
import sys

from drift_tools.operator import main

if __name__ == '__main__':
    sys.exit(main(['bag', *sys.argv[1:]]))
