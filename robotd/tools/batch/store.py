"""The results folder of ``robotd replay-many --out DIR``.

```
DIR/rows.jsonl                   one JSON object per finished replay, appended (and fsynced) as it
                                 arrives: a Ctrl-C or a crash keeps every finished row
DIR/trajectories/KEY.txt         its trajectory (TUM, robot frame), byte for byte what
                                 `robotd replay SOURCE --out T.txt` writes; KEY.cov.txt the pose
                                 covariance; KEY.truth.txt the source's ground truth (when it has one)
DIR/digests.json                 recordings' SHA-256 by (path, size, mtime, inode)
DIR/results.json, table.md,      the last run's table (robotd.tools.batch.table)
DIR/table.csv
```

A row's key is the SHA-256 of (source digest, configuration digest, robotd version): a rerun
with the same data, settings and code finds it and skips the replay; a row whose replay timed out,
ran out of memory, lost its worker or was interrupted is run again (``jobs.DONE_STATUSES``).
Later rows of the same key replace earlier ones. One run at a time writes a folder (a lock).
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
from pathlib import Path
from typing import Any

from robotd.core.errors import InputError
from robotd.tools.batch.jobs import DONE_STATUSES

ROWS = "rows.jsonl"
TRAJECTORIES = "trajectories"


def row_key(source_digest: str, config_digest: str, version: str) -> str:
    return hashlib.sha256(f"{source_digest}\n{config_digest}\n{version}\n".encode()).hexdigest()[:24]


def read_rows(path: Path) -> list[dict[str, Any]]:
    """The rows of a rows.jsonl (a torn last line, from a killed run, is left out)."""
    rows: list[dict[str, Any]] = []
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return rows
    for line in text.splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and "key" in row:
            rows.append(row)
    return rows


class ResultStore:
    """Rows by key, and where trajectories go (module docstring)."""

    def __init__(self, out_dir: str | Path) -> None:
        self.dir = Path(out_dir)
        try:
            (self.dir / TRAJECTORIES).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise InputError(f"--out {self.dir}: {exc.strerror or exc}") from None
        self._lock_fd = os.open(self.dir / ".lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(self._lock_fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self._lock_fd)
            raise InputError(f"--out {self.dir}: another replay-many is writing there; give this one its own") from None
        self.rows: dict[str, dict[str, Any]] = {r["key"]: r for r in read_rows(self.dir / ROWS)}
        self._file = open(self.dir / ROWS, "a", encoding="utf-8")  # closed in close()
        if self._file.tell() > 0 and not (self.dir / ROWS).read_bytes().endswith(b"\n"):
            self._file.write("\n")  # a line torn by a killed run stays alone (read_rows skips it)

    def reload(self) -> None:
        """The rows as rows.jsonl has them: a Ctrl-C between a row's fsync and its entry here
        (``add``) must not leave the table without a replay the folder keeps."""
        self._file.flush()
        self.rows.update({r["key"]: r for r in read_rows(self.dir / ROWS)})

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self._file.close()
        with contextlib.suppress(OSError):
            os.close(self._lock_fd)

    def __enter__(self) -> ResultStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def done(self, key: str) -> dict[str, Any] | None:
        row = self.rows.get(key)
        return row if row is not None and row.get("status") in DONE_STATUSES else None

    def path(self, rel: str) -> Path:
        return self.dir / rel

    def add(self, row: dict[str, Any]) -> dict[str, Any]:
        """Write the row's files, append the row without their text; returns the stored row."""
        row = dict(row)
        key = row["key"]
        for field, suffix, name in (
            ("trajectory_text", ".txt", "trajectory"),
            ("covariance_text", ".cov.txt", "covariance"),
            ("truth_text", ".truth.txt", "truth"),
        ):
            text = row.pop(field, None)
            if text is None:
                continue
            rel = f"{TRAJECTORIES}/{key}{suffix}"
            data = text.encode("ascii")
            tmp = self.dir / f"{rel}.tmp"
            tmp.write_bytes(data)
            os.replace(tmp, self.dir / rel)
            row[name] = rel
            row[f"{name}_sha256"] = hashlib.sha256(data).hexdigest()
        self._file.write(json.dumps(row, sort_keys=True) + "\n")
        self._file.flush()
        os.fsync(self._file.fileno())
        self.rows[key] = row
        return row
