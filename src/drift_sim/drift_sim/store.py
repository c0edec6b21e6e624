"""The run store of a campaign: one JSON line per finished run, appended as it finishes.

A row carries its run's whole configuration and its config hash (``key``); a campaign skips the
jobs whose key has a row, so rerunning an interrupted command resumes it. Each row is flushed
and synced before the next run is looked at: a kill loses at most the run in flight. A line cut
short by a kill mid-write is no finished run and is dropped on the next append; a last row
that is whole but lacks its newline (an edited file) is kept. Rows of runs that ended in an
error are run again; the newest row of a key wins.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from drift_control.params import ParamError


class RunStore:
    """Finished runs by config hash; in memory only when ``path`` is None.

    Parameters
    ----------
    path : path, optional
        The JSON lines file; read if it exists, created on the first ``add``.
    """

    def __init__(self, path: str | os.PathLike | None = None):
        self.path = Path(path) if path else None
        self._rows: dict[str, dict] = {}
        self._end = 0       # bytes up to the last complete row
        self._newline = b''  # what the next append writes first
        if self.path is not None and self.path.exists():
            self._load()

    def _load(self) -> None:
        data = self.path.read_bytes()
        self._end = data.rfind(b'\n') + 1
        for number, line in enumerate(data[:self._end].splitlines(), 1):
            if not line.strip():
                continue
            try:
                row = json.loads(line)
                key = row['key']
            except (ValueError, KeyError, TypeError):
                raise ParamError(f'{self.path}:{number}: not a row of a campaign store (a JSON '
                                 'object with a "key")') from None
            self._rows[key] = row
        tail = data[self._end:]
        if tail.strip():
            try:
                row = json.loads(tail)
                self._rows[row['key']] = row
            except (ValueError, KeyError, TypeError):
                return       # cut short by a kill: dropped on the next append
            self._end, self._newline = len(data), b'\n'

    def __len__(self) -> int:
        return len(self._rows)

    def __contains__(self, key: str) -> bool:
        """A finished run: a row that is not an error."""
        row = self._rows.get(key)
        return row is not None and row.get('outcome') != 'error'

    def get(self, key: str) -> dict | None:
        """The newest row of ``key`` (errors included), or None."""
        return self._rows.get(key)

    def rows(self) -> list[dict]:
        """Every row, the newest of each key, in the order first stored."""
        return list(self._rows.values())

    def add(self, row: dict) -> None:
        """Store a finished run: appended, flushed and synced before this returns."""
        self._rows[row['key']] = row
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        line = json.dumps(row, default=str) + '\n'
        with open(self.path, 'ab') as fh:
            if fh.tell() > self._end:      # a half-written line of a killed campaign
                fh.truncate(self._end)
            fh.write(self._newline + line.encode())
            fh.flush()
            os.fsync(fh.fileno())
            self._end, self._newline = fh.tell(), b''


__all__ = ['RunStore']
