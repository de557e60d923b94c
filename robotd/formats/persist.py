"""Map persistence: atomic, versioned, checked; a bad file is moved aside, never overwritten.

File layout (little-endian): ``b"RBTDMAP\\x01"`` magic | u64 payload length | CBOR payload |
u32 CRC-32 of the payload. The payload is a CBOR map with ``schema`` = ``robotd.state/1``,
``robot``, ``saved_unix_s``, ``t_ns``, and ``state`` (the estimator's and the landmark
database's arrays, see robotd.formats.codec). Writes go to a temporary file in the same directory, are
fsynced, renamed over the old file, and the directory is fsynced: a power cut leaves either the
old or the new map, never a torn one.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import time
import zlib
from pathlib import Path
from typing import Any

import cbor2

from robotd.core.errors import PersistenceError
from robotd.formats.codec import pack_tree, unpack_tree

logger = logging.getLogger("robotd.persist")  # its name before the layer packages: users filter by it

MAGIC = b"RBTDMAP\x01"
STATE_SCHEMA = "robotd.state/1"
MAP_FILENAME = "map.robotd"


def default_state_dir(configured: str = "") -> Path:
    if configured:
        return Path(configured)
    env = os.environ.get("STATE_DIRECTORY")
    if env:
        return Path(env.split(":")[0])
    return Path(os.environ.get("XDG_STATE_HOME", Path.home() / ".local" / "state")) / "robotd"


COUNTER_FILENAME = "reset_counter"
LOCK_FILENAME = "robotd.lock"


class StateDirLock:
    """One robotd per state directory: an exclusive ``flock`` on ``state_dir/robotd.lock``, held while
    the daemon runs (the kernel drops it when the process dies, however it dies), and the directory's
    owner, the robot id written in that file.

    Two robotd sharing a state directory would resume from and save over one map (a second rover's
    map overwriting the first's, or the first's rotated away as an earlier map), and share one reset
    counter. So a second robotd on a directory in use is refused, and so is a robot whose id is not
    the directory's owner's (a rover's id is its state's name: hand the directory over by deleting the
    lock file). A directory that cannot be written (read-only) is not locked: nothing will be saved
    there either."""

    def __init__(self, state_dir: Path, robot_id: str) -> None:
        self.dir = Path(state_dir)
        self.path = self.dir / LOCK_FILENAME
        self.robot_id = robot_id
        self._fd: int | None = None

    def __enter__(self) -> StateDirLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def acquire(self) -> None:
        import fcntl

        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            logger.info("state directory %s not locked (%s): nothing will be saved there", self.dir, exc.strerror)
            return
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            owner, pid = self._read(fd)
            os.close(fd)
            raise PersistenceError(
                f"persistence.state_dir {self.dir} is in use by robotd {owner or '?'} (pid {pid or '?'}): two robotd "
                f"must not share a state directory (each would resume from and save over the other's map); give "
                f'this one its own, e.g. persistence.state_dir = "{self.dir / self.robot_id}"'
            ) from None
        owner, _ = self._read(fd)
        if owner and owner != self.robot_id:
            os.close(fd)
            raise PersistenceError(
                f"persistence.state_dir {self.dir} holds the state of robot {owner!r}, not of {self.robot_id!r} "
                f"(robot.id): give this robot its own state_dir, e.g. {self.dir / self.robot_id}, or delete "
                f"{self.path} to hand the directory over"
            )
        try:
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{self.robot_id} {os.getpid()}\n".encode(), 0)
        except OSError as exc:
            logger.warning("%s: could not record the owner (%s)", self.path, exc.strerror or exc)
        self._fd = fd

    @staticmethod
    def _read(fd: int) -> tuple[str | None, str | None]:
        try:
            words = os.pread(fd, 256, 0).decode("utf-8", "replace").split()
        except OSError:
            return None, None
        return (words[0] if words else None), (words[1] if len(words) > 1 else None)

    def release(self) -> None:
        # the file stays (it names the directory's owner); only the lock goes
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None


class CounterFile:
    """One small integer kept across runs in ``state_dir/reset_counter``: the last MAVLink
    ``reset_counter`` robotd sent, so the next run starts at a different value and the autopilot
    takes its first pose as a new segment (docs/mavlink.md §5). Written atomically (a temporary
    file renamed over it); anything unreadable is None, and a failed write is logged, not raised:
    the pose stream must never wait on it."""

    def __init__(self, state_dir: Path) -> None:
        self.path = Path(state_dir) / COUNTER_FILENAME
        self.failures = 0

    def load(self) -> int | None:
        try:
            text = self.path.read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError):
            return None
        return int(text) if text.isdigit() and int(text) < 256 else None

    def save(self, value: int) -> bool:
        tmp = self.path.with_name(f".{COUNTER_FILENAME}.{os.getpid()}.tmp")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(f"{int(value) & 0xFF}\n", encoding="ascii")
            os.replace(tmp, self.path)
        except OSError as exc:
            self.failures += 1
            if self.failures in (1, 10, 100):
                logger.warning("%s: reset counter not saved (%d so far): %s", self.path, self.failures, exc)
            with contextlib.suppress(OSError):
                tmp.unlink()
            return False
        return True


class MapStore:
    """Saves and loads the robot's map and pose under ``state_dir``."""

    def __init__(self, state_dir: Path, robot_id: str) -> None:
        self.dir = Path(state_dir)
        self.robot_id = robot_id
        self.path = self.dir / MAP_FILENAME
        self.saves = 0
        self.failures = 0
        # a map that failed to resume and could not be moved aside: never written over
        self.protected: str | None = None

    def _refuse_if_protected(self) -> None:
        if self.protected is not None:
            self.failures += 1
            raise PersistenceError(
                f"{self.path}: the map there failed to resume ({self.protected}) and could not be moved aside, "
                "so it is not written over"
            )

    def save(self, state: dict[str, Any], t_ns: int, handover: dict[str, Any] | None = None) -> Path:
        """Write ``state`` atomically; ``handover``: the autopilot's pose at the saved pose's frame
        (robotd.daemon.handover), kept beside the state when given."""
        self._refuse_if_protected()
        doc: dict[str, Any] = {
            "schema": STATE_SCHEMA,
            "robot": self.robot_id,
            "saved_unix_s": time.time(),
            "t_ns": int(t_ns),
            "state": pack_tree(state),
        }
        if handover is not None:
            doc["handover"] = pack_tree(handover)
        payload = cbor2.dumps(doc)
        blob = MAGIC + struct.pack("<Q", len(payload)) + payload + struct.pack("<I", zlib.crc32(payload))
        tmp = self.path.with_name(f".{MAP_FILENAME}.{os.getpid()}.tmp")
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_CLOEXEC, 0o640)
            try:
                view = memoryview(blob)
                while view:
                    n = os.write(fd, view)
                    view = view[n:]
                os.fsync(fd)
            finally:
                os.close(fd)
            os.replace(tmp, self.path)
            dfd = os.open(self.dir, os.O_RDONLY | os.O_DIRECTORY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError as exc:
            self.failures += 1
            try:
                tmp.unlink()
            except OSError:
                pass
            raise PersistenceError(
                f"{self.path}: map not saved ({exc.strerror or exc}); the previous map is kept"
            ) from exc
        self.saves += 1
        return self.path

    def exists(self) -> bool:
        return self.path.exists()

    def remove_orphans(self) -> list[Path]:
        """Delete the temporary files of saves that never finished (a process killed mid-save
        leaves ``.map.robotd.<pid>.tmp``; repeated watchdog restarts would fill the disk). A file
        whose process still runs (another robotd saving into this directory) is left alone."""
        removed: list[Path] = []
        for tmp in self.dir.glob(f".{MAP_FILENAME}.*.tmp"):
            pid_text = tmp.name[len(MAP_FILENAME) + 2 : -len(".tmp")]
            if pid_text.isdigit() and int(pid_text) != os.getpid() and _alive(int(pid_text)):
                continue
            try:
                size = tmp.stat().st_size
                tmp.unlink()
            except OSError as exc:
                logger.warning("could not remove the unfinished save %s: %s", tmp, exc.strerror or exc)
                continue
            removed.append(tmp)
            logger.info("removed %s, an unfinished save (%.1f MB) of a process that is gone", tmp, size / 1e6)
        return removed

    def keep_previous(self, keep: int) -> Path | None:
        """Before a run that did not resume from it overwrites the saved map: rename it to
        ``map.<time>.robotd`` (the time it was last written) and delete the oldest such maps beyond
        ``keep``, saying so in the log. Returns where the previous map went (None: there was none,
        or ``keep`` is 0 and it will be overwritten, which is logged too)."""
        self._refuse_if_protected()
        if not self.path.exists():
            return None
        if keep <= 0:
            logger.warning("the saved map %s will be overwritten (persistence.keep_maps = 0)", self.path)
            return None
        stamp = time.strftime("%Y%m%dT%H%M%S", time.localtime(self.path.stat().st_mtime))
        kept = self.path.with_name(f"map.{stamp}.robotd")
        k = 1
        while kept.exists():
            kept = self.path.with_name(f"map.{stamp}-{k}.robotd")
            k += 1
        try:
            os.replace(self.path, kept)
        except OSError as exc:
            raise PersistenceError(f"{self.path}: could not keep the previous map ({exc.strerror or exc})") from exc
        logger.info("kept the previous map as %s (persistence.keep_maps = %d)", kept, keep)
        for old in self.kept_maps()[:-keep]:
            try:
                old.unlink()
                logger.info("removed the oldest kept map %s (persistence.keep_maps = %d)", old, keep)
            except OSError as exc:
                logger.warning("could not remove the old map %s: %s", old, exc.strerror or exc)
        return kept

    def kept_maps(self) -> list[Path]:
        """The earlier maps kept by :meth:`keep_previous`, oldest first."""
        return sorted(self.dir.glob("map.2*.robotd"))

    def load(self) -> dict[str, Any]:
        """The saved state. A corrupt or foreign file is moved aside and PersistenceError raised."""
        try:
            blob = self.path.read_bytes()
        except FileNotFoundError as exc:
            raise PersistenceError(f"{self.path}: no saved map") from exc
        except OSError as exc:
            raise PersistenceError(f"{self.path}: cannot read saved map ({exc.strerror or exc})") from exc
        try:
            return self._parse(blob)
        except PersistenceError as exc:
            raise PersistenceError(self.set_aside(str(exc))) from None

    def _parse(self, blob: bytes) -> dict[str, Any]:
        if blob[: len(MAGIC)] != MAGIC:
            raise PersistenceError(f"{self.path}: not a robotd map (magic {blob[:8]!r}, expected {MAGIC!r})")
        if len(blob) < len(MAGIC) + 12:
            raise PersistenceError(f"{self.path}: truncated ({len(blob)} bytes)")
        (n,) = struct.unpack_from("<Q", blob, len(MAGIC))
        start = len(MAGIC) + 8
        if len(blob) != start + n + 4:
            raise PersistenceError(f"{self.path}: truncated or padded ({len(blob)} bytes, header says {start + n + 4})")
        payload = blob[start : start + n]
        (crc,) = struct.unpack_from("<I", blob, start + n)
        if zlib.crc32(payload) != crc:
            raise PersistenceError(f"{self.path}: checksum mismatch (corrupt file)")
        try:
            msg = cbor2.loads(payload)
        except Exception as exc:
            raise PersistenceError(f"{self.path}: payload is not CBOR ({exc})") from exc
        if not isinstance(msg, dict) or msg.get("schema") != STATE_SCHEMA:
            got = msg.get("schema") if isinstance(msg, dict) else type(msg).__name__
            raise PersistenceError(f"{self.path}: schema {got!r}, expected {STATE_SCHEMA!r}")
        if msg.get("robot") != self.robot_id:
            raise PersistenceError(f"{self.path}: map of robot {msg.get('robot')!r}, this is {self.robot_id!r}")
        if "state" not in msg:
            raise PersistenceError(f"{self.path}: no state in the map")
        state = unpack_tree(msg["state"])  # cbor2 refuses nesting deeper than 400 levels
        if not isinstance(state, dict):
            raise PersistenceError(f"{self.path}: state is not a table")
        handover = None
        if "handover" in msg:  # optional: a bad one costs the handover, never the map
            try:
                handover = unpack_tree(msg["handover"], "handover")
            except (PersistenceError, ValueError, TypeError) as exc:
                logger.warning("%s: the autopilot handover is unreadable and ignored: %s", self.path, exc)
        return {
            "t_ns": msg.get("t_ns", 0),
            "saved_unix_s": msg.get("saved_unix_s"),
            "state": state,
            "handover": handover,
        }

    def set_aside(self, reason: str) -> str:
        """A map that cannot be resumed (``reason``, one line): moved aside to
        ``map.robotd.bad-<time>``, never overwritten; when it cannot be moved (a read-only state
        directory), left in place and ignored, and this store then refuses to save over it.
        Returns the line to log: the reason and where the map went."""
        reason = " ".join(reason.split())  # one line, whatever a library put in its message
        try:
            aside = self.move_aside()
        except OSError as exc:
            self.protected = reason
            return (
                f"{reason}; could not move it aside ({exc.strerror or exc}): left in place and ignored, "
                "starting a new map that will not be saved over it"
            )
        return f"{reason}; moved aside to {aside.name}, starting a new map"

    def move_aside(self) -> Path:
        """Rename the map to ``map.robotd.bad-<time>[-k]`` (OSError when it cannot)."""
        stamp = time.strftime("%Y%m%dT%H%M%S")
        aside = self.path.with_name(f"{MAP_FILENAME}.bad-{stamp}")
        k = 1
        while aside.exists():
            aside = self.path.with_name(f"{MAP_FILENAME}.bad-{stamp}-{k}")
            k += 1
        os.replace(self.path, aside)
        return aside


def _alive(pid: int) -> bool:
    """Whether a process with this pid exists (signal 0 probes without signalling)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # it exists, under another user
    return True
