"""MCAP recording: round trip (bit-identical images, equal odometry/poses), determinism, Foxglove
schemas, atomic finish and write errors, replay through the driver registry."""

from __future__ import annotations

import errno
import io
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from drivers import open_camera
from drivers.dataset import DatasetVehicle, open_mcap_vehicle
from robotd.errors import DatasetError, PersistenceError
from robotd.msgs import Odometry, PoseEstimate, StereoFrame
from robotd.record import SessionReader, SessionWriter, record_session
from robotd.stereo import RectifiedStereo

MODEL = RectifiedStereo(430.34, 322.05, 199.18, 0.0755, 64, 40)
T0 = 5_000_000_000_123  # a monotonic stamp with nanosecond digits


def session(rng: np.random.Generator, n: int = 6) -> list[StereoFrame | Odometry | PoseEstimate]:
    events: list[StereoFrame | Odometry | PoseEstimate] = []
    for i in range(n):
        t = T0 + i * 33_333_333
        # every other sample states its noise (Odometry.cov), the others leave it to the model
        odo_cov = np.diag(rng.uniform(1e-4, 1e-2, 6)) if i % 2 else None
        events.append(Odometry(t - 7, rng.normal(size=3), rng.normal(size=3), source="wheels", cov=odo_cov))
        truth = np.eye(4) if i % 2 else None
        img = lambda: rng.integers(0, 256, (40, 64), dtype=np.uint8)  # noqa: E731
        events.append(StereoFrame(t, 100 + i, img(), img(), True, truth))
        cov = np.diag(rng.uniform(0.01, 1, 6))
        neff = float("nan") if i % 3 == 0 else float(rng.uniform(1, 100))
        events.append(PoseEstimate(t, rng.normal(size=3), rng.normal(size=3), cov, neff, 100))
    return events


def write(path: Path, events: list[Any], **kw: Any) -> SessionWriter:
    with SessionWriter(path, MODEL, {"source": "test://", "seed": 1}, **kw) as w:
        for e in events:
            if isinstance(e, StereoFrame):
                w.write_frame(e)
            elif isinstance(e, Odometry):
                w.write_odometry(e)
            else:
                w.write_pose(e)
    return w


def assert_same(a: Any, b: Any) -> None:
    assert type(a) is type(b) and a.t_ns == b.t_ns
    if isinstance(a, StereoFrame):
        assert a.seq == b.seq and a.rectified == b.rectified
        assert a.left.dtype == b.left.dtype == np.uint8
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)  # bit-identical
        assert (a.truth_T_world_robot is None) == (b.truth_T_world_robot is None)
        if a.truth_T_world_robot is not None:
            assert np.array_equal(a.truth_T_world_robot, b.truth_T_world_robot)
    elif isinstance(a, Odometry):
        assert np.array_equal(a.vel_R_mps, b.vel_R_mps) and np.array_equal(a.rate_R_radps, b.rate_R_radps)
        assert a.source == b.source
        assert (a.cov is None and b.cov is None) or np.array_equal(a.cov, b.cov)  # type: ignore[arg-type]
    else:
        for k in ("xyz_W_m", "rpy_rad", "cov"):
            assert np.array_equal(getattr(a, k), getattr(b, k))
        assert (np.isnan(a.neff) and np.isnan(b.neff)) or a.neff == b.neff
        assert a.n_particles == b.n_particles


@pytest.mark.parametrize("image_format", ["png", "raw"])
def test_round_trip_is_exact_and_deterministic(tmp_path: Path, rng: np.random.Generator, image_format: str) -> None:
    events = session(rng)
    path = tmp_path / "s.mcap"
    write(path, events, image_format=image_format)
    assert path.is_file() and not (tmp_path / "s.mcap.tmp").exists()
    reader = SessionReader(path)
    assert reader.calibration == MODEL
    assert reader.meta == {"source": "test://", "seed": 1}
    back = list(reader.events())
    assert len(back) == len(events)
    for a, b in zip(events, back):
        assert_same(a, b)
    again = list(SessionReader(path).events())
    for a, b in zip(back, again):
        assert_same(a, b)


def test_foxglove_channels_and_calibration(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "s.mcap"
    write(path, session(rng, 3))
    with open(path, "rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        assert summary is not None
        by_topic = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        assert all(c.message_encoding == "json" for c in summary.channels.values())
        assert by_topic["/camera/left/image"].name == "foxglove.CompressedImage"
        assert by_topic["/camera/right/calibration"].name == "foxglove.CameraCalibration"
        assert by_topic["/robotd/pose"].name == "foxglove.PoseInFrame"
        assert all(s.encoding == "jsonschema" for s in summary.schemas.values())
        msgs = {ch.topic: json.loads(m.data) for _, ch, m in r.iter_messages()}
    cal = msgs["/camera/right/calibration"]
    assert cal["P"][3] == pytest.approx(-MODEL.f_px * MODEL.baseline_m)  # ROS CameraInfo Tx = -f b
    assert cal["K"][2] == MODEL.px and cal["width"] == 64
    img = msgs["/camera/left/image"]
    assert img["format"] == "png" and set(img["timestamp"]) == {"sec", "nsec"}
    q = msgs["/robotd/pose"]["pose"]["orientation"]
    assert np.linalg.norm([q["x"], q["y"], q["z"], q["w"]]) == pytest.approx(1.0)


def test_replay_through_driver_registry(tmp_path: Path, rng: np.random.Generator) -> None:
    events = session(rng)
    path = tmp_path / "s.mcap"
    write(path, events)
    frames = [e for e in events if isinstance(e, StereoFrame)]
    with open_camera(str(path)) as cam:  # a bare .mcap path selects the mcap driver
        assert cam.rectified_model() == MODEL
        got = list(cam.frames())
    assert [f.t_ns for f in got] == [f.t_ns for f in frames]
    with open_camera(f"mcap://{path}?start=1&stride=2") as cam:
        assert [f.seq for f in cam.frames()] == [101, 103, 105]
    odo = list(open_mcap_vehicle(f"mcap://{path}").odometry())
    for a, b in zip([e for e in events if isinstance(e, Odometry)], odo, strict=True):
        assert_same(a, b)


class FullDisk(io.RawIOBase):
    """A file that accepts ``capacity`` bytes, then fails like a full disk."""

    def __init__(self, path: Path, capacity: int) -> None:
        self._f = open(path, "wb")
        self.capacity = capacity

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        if self._f.tell() + len(b) > self.capacity:
            raise OSError(errno.ENOSPC, "No space left on device")
        return self._f.write(b)

    def tell(self) -> int:
        return self._f.tell()

    def flush(self) -> None:
        self._f.flush()

    def fileno(self) -> int:
        return self._f.fileno()

    def close(self) -> None:
        super().close()
        self._f.close()


def test_disk_full_raises_and_keeps_the_finalised_file(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "s.mcap"
    write(path, session(rng, 2))
    before = path.read_bytes()
    events = session(rng, 40)
    with pytest.raises(PersistenceError, match=r"No space left.*previous s.mcap left untouched"):
        write(path, events, chunk_size=16 * 1024, opener=lambda p: FullDisk(p, 40_000))
    assert path.read_bytes() == before
    assert not (tmp_path / "s.mcap.tmp").exists()
    assert len(list(SessionReader(path).frames())) == 2


def test_writer_refuses_after_close_and_bad_input(tmp_path: Path, rng: np.random.Generator) -> None:
    w = write(tmp_path / "s.mcap", session(rng, 1))
    with pytest.raises(PersistenceError, match="closed"):
        w.write_odometry(Odometry(1, np.zeros(3), np.zeros(3)))
    with pytest.raises(Exception, match="JSON"):
        SessionWriter(tmp_path / "t.mcap", MODEL, {"bad": object()})


def test_foreign_or_corrupt_files_are_refused(tmp_path: Path) -> None:
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    with pytest.raises(PersistenceError, match="junk.mcap"):
        SessionReader(junk)
    with pytest.raises(DatasetError, match="not found"):
        open_camera(str(tmp_path / "missing.mcap"))


def test_record_session_interleaves_odometry(tmp_path: Path, rng: np.random.Generator) -> None:
    frames = [e for e in session(rng, 5) if isinstance(e, StereoFrame)]
    odo = [Odometry(T0 + 1000 * i, np.zeros(3), np.zeros(3), "sim") for i in range(7)]

    class Cam:
        def frames(self, timeout_s: float = 1.0):
            yield from frames

    path = tmp_path / "r.mcap"
    with SessionWriter(path, MODEL, {}) as w:
        summary = record_session(Cam(), DatasetVehicle("test://", odo), w, duration_s=0, max_frames=4)
    assert summary["frames"] == 4 and summary["odometry"] == 7
    r = SessionReader(path)
    assert [f.seq for f in r.frames()] == [f.seq for f in frames[:4]]
    assert [o.t_ns for o in r.odometry()] == [o.t_ns for o in odo]


def test_odometry_recorded_before_samples_stated_their_noise_still_reads() -> None:
    from robotd.record import odometry_from_json

    o = odometry_from_json({"t_ns": 5, "vel_R_mps": [1.0, 0.0, 0.0], "rate_R_radps": [0.0, 0.0, 0.1], "source": "sim"})
    assert o.cov is None and o.t_ns == 5 and o.source == "sim"
