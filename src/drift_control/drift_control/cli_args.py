"""What the command-line scripts share: argument types (a bad value is one argparse line,
exit 2) and where a tool may write: never over or into its inputs, and somewhere it can.

Tools check their output paths with ``output_problem`` before the work (a campaign's summary or
a replay's report is written after minutes of it) and write with ``write_text``; both give a
bad path as one line for the caller to print.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path


def _checked(text: str, convert, ok, expected: str):
    """``convert(text)`` if it converts and ``ok`` holds, else argparse's one-line error."""
    try:
        value = convert(text)
    except ValueError:
        value = None
    if value is None or not ok(value):
        raise argparse.ArgumentTypeError(f'expected {expected}, got {text!r}')
    return value


def seed(text: str) -> int:
    """A seed >= 0."""
    return _checked(text, int, lambda v: v >= 0, 'an integer >= 0')


def seconds(text: str) -> float:
    """A duration >= 0 [s], finite."""
    return _checked(text, float, lambda v: 0.0 <= v < math.inf, 'seconds >= 0')


def natural(text: str) -> int:
    """An integer >= 0 (a number of passes, 0 meaning "until stopped")."""
    return seed(text)


def nonnegative(text: str) -> float:
    """A finite number >= 0 (a rate where 0 means "unpaced")."""
    return _checked(text, float, lambda v: 0.0 <= v < math.inf, 'a finite number >= 0')


def count(text: str) -> int:
    """An integer >= 1 (repeats, jobs, workers)."""
    return _checked(text, int, lambda v: v >= 1, 'an integer >= 1')


def positive(text: str) -> float:
    """A finite number > 0 (a rate, a friction coefficient)."""
    return _checked(text, float, lambda v: 0.0 < v < math.inf, 'a finite number > 0')


def output_problem(path, inputs=(), directory: bool = False) -> str | None:
    """Why ``path`` cannot take a tool's output, or None.

    ``inputs``: the files and directories the tool reads (a bag directory, a run store, a DBC):
    the output may be none of them and, for a directory input, not inside it (a bag is
    evidence). ``directory``: the output is a directory of files. The place is tried for real
    (a probe file created and removed; an existing file opened for appending, unchanged), as
    permission bits say little to root.
    """
    out = Path(path).expanduser().resolve()
    for source in inputs:
        if source is None:
            continue
        src = Path(source).expanduser().resolve()
        if out == src:
            return f'{path}: is the input {source}; a tool never writes over its input'
        if src.is_dir() and out.is_relative_to(src):
            return f'{path}: is inside the input {source}; a tool never writes into its input'
    if directory:
        if out.exists() and not out.is_dir():
            return f'{path}: exists and is not a directory'
        return _probe(out / f'.probe-{os.getpid()}', path)
    if out.is_dir():
        return f'{path}: is a directory'
    if out.exists():
        try:
            with open(out, 'ab'):
                pass
        except OSError as err:
            return f'{path}: cannot be written ({err.strerror or err})'
        return None
    return _probe(out, path)


def _probe(file: Path, named) -> str | None:
    """Create ``file`` (and its missing parents) and remove them again; the failure, or None."""
    made = [d for d in (file.parent, *file.parent.parents) if not d.exists()]
    try:
        file.parent.mkdir(parents=True, exist_ok=True)
        with open(file, 'xb'):
            pass
        file.unlink()
    except OSError as err:
        return f'{named}: cannot be written ({err.strerror or err})'
    finally:
        for d in made:   # innermost first; what the tool will make again
            try:
                d.rmdir()
            except OSError:
                break
    return None


def write_text(path, text: str) -> str | None:
    """Write ``text`` to ``path`` (its parents made); the failure as one line, or None."""
    try:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(text)
    except OSError as err:
        return f'{path}: cannot be written ({err.strerror or err})'
    return None


__all__ = ['count', 'natural', 'nonnegative', 'output_problem', 'positive', 'seconds',
           'seed', 'write_text']
