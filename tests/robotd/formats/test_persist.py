"""Map persistence: atomic round trip, corrupt/foreign files moved aside, full disk keeps the old map."""

from __future__ import annotations

import errno
import os
import struct
import zlib
from pathlib import Path

import cbor2
import numpy as np
import pytest

from robotd.core.errors import PersistenceError
from robotd.core.msgs import LandmarkMap
from robotd.daemon.sdnotify import Notifier
from robotd.formats.codec import decode_map, encode_map
from robotd.formats.persist import LOCK_FILENAME, MAGIC, STATE_SCHEMA, CounterFile, MapStore, StateDirLock
from tests.support.tolerances import FLOAT32_ROUNDING_TOL


def _state(rng: np.random.Generator) -> dict:
    return {
        "filter": "fastslam2",
        "pose": rng.normal(size=(100, 6)),
        "lm_mean": rng.normal(size=(100, 50, 3)).astype(np.float32),
        "ids": np.arange(50, dtype=np.int64),
        "nested": {"desc": rng.integers(0, 255, (50, 32), dtype=np.uint8), "n": 3},
    }


def test_round_trip_is_exact(tmp_path: Path, rng: np.random.Generator) -> None:
    store = MapStore(tmp_path, "r1")
    st = _state(rng)
    store.save(st, t_ns=123)
    got = MapStore(tmp_path, "r1").load()
    assert got["t_ns"] == 123
    s = got["state"]
    assert s["filter"] == "fastslam2" and s["nested"]["n"] == 3
    for k in ("pose", "lm_mean", "ids"):
        assert s[k].dtype == st[k].dtype and np.array_equal(s[k], st[k])
    assert np.array_equal(s["nested"]["desc"], st["nested"]["desc"])
    assert not list(tmp_path.glob(".*.tmp")), "temporary file left behind"


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda b: b"GARBAGE!" + b[8:], "not a robotd map"),
        (lambda b: b[:-10], "truncated"),
        (lambda b: b[:40] + bytes([b[40] ^ 0xFF]) + b[41:], "checksum mismatch"),
    ],
)
def test_corrupt_file_is_moved_aside_never_overwritten(
    tmp_path: Path, rng: np.random.Generator, mutate, message
) -> None:
    store = MapStore(tmp_path, "r1")
    store.save(_state(rng), 1)
    bad = mutate(store.path.read_bytes())
    store.path.write_bytes(bad)
    with pytest.raises(PersistenceError, match=message) as err:
        store.load()
    assert "moved aside" in str(err.value)
    aside = list(tmp_path.glob("map.robotd.bad-*"))
    assert len(aside) == 1 and aside[0].read_bytes() == bad
    assert not store.path.exists()


def test_foreign_robot_map_is_refused(tmp_path: Path, rng: np.random.Generator) -> None:
    MapStore(tmp_path, "r1").save(_state(rng), 1)
    with pytest.raises(PersistenceError, match="map of robot 'r1', this is 'r2'"):
        MapStore(tmp_path, "r2").load()


def test_full_disk_keeps_previous_map(tmp_path: Path, rng: np.random.Generator, monkeypatch) -> None:
    store = MapStore(tmp_path, "r1")
    store.save(_state(rng), 1)
    before = store.path.read_bytes()
    real_write = os.write

    def full(fd: int, data) -> int:  # the disk fills up halfway through
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "write", full)
    with pytest.raises(PersistenceError, match="No space left on device.*previous map is kept"):
        store.save(_state(rng), 2)
    monkeypatch.setattr(os, "write", real_write)
    assert store.path.read_bytes() == before
    assert MapStore(tmp_path, "r1").load()["t_ns"] == 1
    assert not list(tmp_path.glob(".*.tmp"))


def test_map_message_round_trip(rng: np.random.Generator) -> None:
    A = rng.normal(size=(20, 3, 3))
    lm = LandmarkMap(np.arange(20, dtype=np.int64) * 7, rng.normal(size=(20, 3)), A @ np.swapaxes(A, 1, 2))
    meta, back = decode_map(encode_map("r1", 5, lm, seq=3))
    assert meta["robot"] == "r1" and meta["seq"] == 3 and meta["n"] == 20
    assert np.array_equal(back.ids, lm.ids)
    # the map file stores float32
    assert np.allclose(back.xyz_W_m, lm.xyz_W_m, atol=FLOAT32_ROUNDING_TOL)
    assert np.allclose(back.cov_W, lm.cov_W, rtol=FLOAT32_ROUNDING_TOL, atol=FLOAT32_ROUNDING_TOL)
    with pytest.raises(PersistenceError, match="expected schema"):
        decode_map(b"\xa1aa\x01")


def test_sd_notify_datagrams(tmp_path: Path) -> None:
    import socket

    path = str(tmp_path / "notify.sock")
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    srv.bind(path)
    srv.settimeout(1.0)
    n = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "4000000"})
    assert n.enabled and n.watchdog_interval_s == pytest.approx(2.0)
    n.ready("tracking")
    assert srv.recv(1024) == b"READY=1\nSTATUS=tracking"
    n.watchdog()
    assert srv.recv(1024) == b"WATCHDOG=1"
    n.stopping()
    assert srv.recv(1024).startswith(b"STOPPING=1")
    n.close()
    srv.close()
    off = Notifier({})
    assert not off.enabled and off.ready() is False


def _sealed(payload: dict) -> bytes:
    """A map file around any payload, with a valid checksum (the layout of robotd.formats.persist)."""
    body = cbor2.dumps(payload)
    return MAGIC + struct.pack("<Q", len(body)) + body + struct.pack("<I", zlib.crc32(body))


GOOD = {"schema": STATE_SCHEMA, "robot": "r1", "saved_unix_s": 0.0, "t_ns": 1}


@pytest.mark.parametrize(
    ("payload", "message"),
    [
        (GOOD, "no state in the map"),
        ({**GOOD, "state": None}, "state is not a table"),
        ({**GOOD, "state": {"x": {"__nd__": {"dtype": "f8,(2", "shape": [1], "data": b""}}}}, "state.x: not a packed"),
        ({**GOOD, "state": {"x": {"__nd__": {"dtype": "<f8", "shape": [2**40] * 2, "data": b""}}}}, "not a packed"),
    ],
)
def test_a_payload_with_a_valid_checksum_and_bad_content_is_moved_aside(tmp_path: Path, payload, message) -> None:
    blob = _sealed(payload)
    (tmp_path / "map.robotd").write_bytes(blob)
    with pytest.raises(PersistenceError, match=message) as err:
        MapStore(tmp_path, "r1").load()
    assert "moved aside to map.robotd.bad-" in str(err.value)
    assert [p.read_bytes() for p in tmp_path.glob("map.robotd.bad-*")] == [blob]


def test_the_reset_counter_file_round_trips_and_forgives_what_it_cannot_read(tmp_path: Path) -> None:
    f = CounterFile(tmp_path / "state")
    assert f.load() is None  # no file: a first run
    assert f.save(7) and f.load() == 7
    assert f.save(256 + 3) and f.load() == 3  # uint8, as on the wire
    for junk in (b"", b"12x\n", b"-1\n", b"300\n", b"\xff\xfe"):
        f.path.write_bytes(junk)
        assert f.load() is None, junk
    # a state directory that cannot be written: counted, not raised
    ro = CounterFile(tmp_path / "file-not-dir")
    (tmp_path / "file-not-dir").write_text("x")
    assert not ro.save(1) and ro.failures == 1


def test_one_robotd_per_state_directory_and_the_directory_keeps_its_robot(tmp_path: Path) -> None:
    """Two robotd on one state directory would resume from and save over one map: the second one is
    refused naming the first (its robot and pid), and so is another robot once the first is gone."""
    state = tmp_path / "state"
    with StateDirLock(state, "r1"):
        assert (state / LOCK_FILENAME).read_text() == f"r1 {os.getpid()}\n"
        with pytest.raises(PersistenceError, match=rf"is in use by robotd r1 \(pid {os.getpid()}\)") as err:
            StateDirLock(state, "r2").acquire()
        assert f'persistence.state_dir = "{state / "r2"}"' in str(err.value)
        with pytest.raises(PersistenceError, match="is in use by robotd r1"):
            StateDirLock(state, "r1").acquire()  # the same robot twice, too
    with StateDirLock(state, "r1"):  # released: the same robot runs again
        pass
    with pytest.raises(PersistenceError, match=r"holds the state of robot 'r1', not of 'r2' \(robot.id\)"):
        StateDirLock(state, "r2").acquire()
    (state / LOCK_FILENAME).unlink()  # handed over
    with StateDirLock(state, "r2"):
        assert (state / LOCK_FILENAME).read_text().split()[0] == "r2"


def test_a_state_directory_that_cannot_be_written_is_not_locked(tmp_path: Path) -> None:
    (tmp_path / "file").write_text("not a directory")
    lock = StateDirLock(tmp_path / "file", "r1")
    lock.acquire()  # logged, not raised: nothing can be saved there either
    lock.release()
