"""Argument types shared by the command-line scripts: a bad value is one argparse line, exit 2."""
from __future__ import annotations

import argparse


def seed(text: str) -> int:
    """A seed >= 0."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f'expected an integer >= 0, got {text!r}')
    return value


def seconds(text: str) -> float:
    """A duration >= 0 [s], finite."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not 0.0 <= value < float('inf'):
        raise argparse.ArgumentTypeError(f'expected seconds >= 0, got {text!r}')
    return value
