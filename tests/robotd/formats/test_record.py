"""MCAP recording: round trip (bit-identical images, equal odometry/poses), determinism, Foxglove
schemas, atomic finish and write errors, replay through the driver registry."""

from __future__ import annotations

import errno
import io
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

from drivers import open_camera
from drivers.dataset import DatasetVehicle, open_mcap_vehicle
from robotd.core.errors import DatasetError, PersistenceError
from robotd.core.msgs import Odometry, PoseEstimate, StereoFrame
from robotd.core.stereo import RectifiedStereo
from robotd.formats.record import SessionReader, SessionWriter, record_session
from tests.support.mcap_decode import decode_all
from tests.support.paths import REPO

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
        exposure = 0 if i % 3 == 0 else 4_000_000 + 17 * i  # some cameras report their exposure
        events.append(StereoFrame(t, 100 + i, img(), img(), True, truth, exposure))
        cov = np.diag(rng.uniform(0.01, 1, 6))
        neff = float("nan") if i % 3 == 0 else float(rng.uniform(1, 100))
        events.append(PoseEstimate(t, rng.normal(size=3), rng.normal(size=3), cov, neff, 100))
    return events


def put(w: SessionWriter, e: Any) -> None:
    """Write one event of :func:`session` with the writer's call for its type."""
    if isinstance(e, StereoFrame):
        w.write_frame(e)
    elif isinstance(e, Odometry):
        w.write_odometry(e)
    else:
        w.write_pose(e)


def write(path: Path, events: list[Any], **kw: Any) -> SessionWriter:
    with SessionWriter(path, MODEL, {"source": "test://", "seed": 1}, **kw) as w:
        for e in events:
            put(w, e)
    return w


def assert_same(a: Any, b: Any) -> None:
    assert type(a) is type(b) and a.t_ns == b.t_ns
    if isinstance(a, StereoFrame):
        assert a.seq == b.seq and a.rectified == b.rectified and a.exposure_ns == b.exposure_ns
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


def test_every_channel_decodes_with_its_declared_foxglove_schema(tmp_path: Path, rng: np.random.Generator) -> None:
    """Format 2: Foxglove's well-known schemas (protobuf) for the images, calibration, poses,
    transforms, trajectory, map and tracks; wall-clock log times with the monotonic capture time
    kept in robotd's fields."""
    from robotd.core.msgs import LandmarkMap, Observations

    path = tmp_path / "s.mcap"
    events = session(rng, 3)
    wall0 = 1_760_000_000_000_000_000  # a wall-clock instant (2025) for the first stamp
    lm = LandmarkMap(np.array([3, 7], np.int64), np.array([[1.0, 2.0, 3.0], [4.0, -5.0, 0.5]]),
                     np.stack([np.diag([0.01, 0.04, 0.09])] * 2))  # fmt: skip
    uv = np.array([[30.0, 20.0, 10.0], [50.0, 41.0, 30.0]])
    with SessionWriter(path, MODEL, {"source": "test://"}, wall_offset_ns=wall0 - T0) as w:
        for e in events:
            put(w, e)
            if isinstance(e, PoseEstimate):
                w.write_features(Observations(e.t_ns, np.ones((2, 3)), np.stack([np.eye(3)] * 2),
                                              np.array([3, 7]), np.array([False, True]), uv))  # fmt: skip
                uv = uv + 1.0
        w.write_map(events[-1].t_ns, lm)
    msgs = decode_all(path)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    names = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert names["/camera/left/image"] == names["/camera/right/image"] == "foxglove.CompressedImage"
    assert names["/camera/right/calibration"] == "foxglove.CameraCalibration"
    assert names["/robotd/pose"] == names["/truth/pose"] == "foxglove.PoseInFrame"
    assert names["/robotd/trajectory"] == names["/truth/trajectory"] == "foxglove.PosesInFrame"
    assert names["/robotd/map"] == "foxglove.PointCloud" and names["/robotd/map_covariance"] == "foxglove.SceneUpdate"
    assert names["/tf"] == "foxglove.FrameTransforms" and names["/camera/left/features"] == "foxglove.ImageAnnotations"
    assert names["/robotd/odometry"] == "foxglove.Odometry"

    # images: raw PNG bytes (no base64), the recorded pixels
    t_img, img = msgs["/camera/left/image"][0]
    assert img.format == "png" and bytes(img.data[:8]) == b"\x89PNG\r\n\x1a\n" and img.frame_id == "camera_left"
    first = next(e for e in events if isinstance(e, StereoFrame))
    assert np.array_equal(cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_UNCHANGED), first.left)
    # wall-clock log time and timestamp; the monotonic capture time stays in robotd's frame info
    assert t_img == wall0 and img.timestamp.seconds * 10**9 + img.timestamp.nanos == wall0
    frame_t, frame_info = msgs["/robotd/frame"][0]
    assert frame_t == wall0 and frame_info["t_ns"] == T0
    odo_t, odo = msgs["/robotd/odometry"][0]
    assert odo_t == wall0 - 7 and dict((kv.key, kv.value) for kv in odo.metadata)["t_ns"] == str(T0 - 7)

    cal = msgs["/camera/right/calibration"][0][1]
    assert cal.P[3] == pytest.approx(-MODEL.f_px * MODEL.baseline_m) and cal.K[2] == MODEL.px and cal.width == 64
    # transforms: robot -> cameras (optical axes, ∓b/2 along the robot's y), world -> robot per pose
    tfs = {(t.parent_frame_id, t.child_frame_id): t for _, m in msgs["/tf"] for t in m.transforms}
    assert tfs[("robot", "camera_left")].translation.y == pytest.approx(-MODEL.baseline_m / 2)
    assert tfs[("robot", "camera_right")].translation.y == pytest.approx(MODEL.baseline_m / 2)
    last_pose = [e for e in events if isinstance(e, PoseEstimate)][-1]
    p = tfs[("world", "robot")].translation
    assert [p.x, p.y, p.z] == pytest.approx(list(last_pose.xyz_W_m))
    q = msgs["/robotd/pose"][-1][1].pose.orientation
    assert np.linalg.norm([q.x, q.y, q.z, q.w]) == pytest.approx(1.0)
    # the trajectory holds every pose written (they are far apart), the truth its two poses
    assert len(msgs["/robotd/trajectory"][-1][1].poses) == 3
    assert len(msgs["/truth/pose"]) == 1 and msgs["/truth/pose"][0][1].frame_id == "world"
    # the map: x, y, z float32 and the id per point, and one ellipsoid per landmark (2σ: 4σ wide)
    pc = msgs["/robotd/map"][0][1]
    pts = np.frombuffer(pc.data, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("id", "<u4")])
    assert pc.point_stride == 16 and [f.name for f in pc.fields] == ["x", "y", "z", "id"]
    assert np.array_equal(pts["id"], [3, 7]) and np.allclose(pts["z"], [3.0, 0.5])
    spheres = msgs["/robotd/map_covariance"][0][1].entities[0].spheres
    assert len(spheres) == 2 and sorted([spheres[0].size.x, spheres[0].size.y, spheres[0].size.z]) == pytest.approx(
        [0.4, 0.8, 1.2]
    )
    # the feature tracks: landmark 3 seen again draws a segment from its previous pixel
    ann = msgs["/camera/left/features"][-1][1]
    lines = [a for a in ann.points if a.type == 4]  # LINE_LIST
    assert len(lines) == 1 and [(pt.x, pt.y) for pt in lines[0].points] == [(31.0, 11.0), (32.0, 12.0)]


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
    from robotd.formats.record import odometry_from_json

    o = odometry_from_json({"t_ns": 5, "vel_R_mps": [1.0, 0.0, 0.0], "rate_R_radps": [0.0, 0.0, 0.1], "source": "sim"})
    assert o.cov is None and o.t_ns == 5 and o.source == "sim"


# ---------------------------------------------------------------------------------------------
# format 1 (robotd's recordings before format 2), damage, interrupted recordings

FORMAT1 = REPO / "tests" / "support" / "data" / "format1_sim_160x100.mcap"


def test_format1_recordings_still_read_and_replay_like_their_format2_copy(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A recording robotd wrote before format 2 (a real one: `robotd record` on sim://, 160×100,
    17 frames) reads as before, and rewritten as format 2 it replays to the same TUM trajectory,
    byte for byte."""
    from robotd.tools.cli import main

    old = SessionReader(FORMAT1)
    assert old.format_version == 1 and old.calibration.width == 160
    events = list(old.events())
    assert old.finished and old.stopped is None
    assert sum(isinstance(e, StereoFrame) for e in events) == 17
    new = tmp_path / "format2.mcap"
    with SessionWriter(new, old.calibration, old.meta, raw_calibration=old.calibration_json["raw"]) as w:
        for e in events:
            put(w, e)
    back = list(SessionReader(new).events())
    assert len(back) == len(events)
    for a, b in zip(events, back):
        assert_same(a, b)
    trajs = []
    for src in (FORMAT1, new):
        out = tmp_path / f"{Path(src).stem}.txt"
        assert main(["replay", str(src), "--out", str(out), "--quiet", "--log-level", "WARNING"]) == 0
        trajs.append(out.read_bytes())
    capsys.readouterr()
    assert trajs[0] == trajs[1] and trajs[0].count(b"\n") == 1 + 17  # the header and one line per frame


def test_a_newer_format_version_is_refused_naming_it(tmp_path: Path, rng: np.random.Generator, monkeypatch) -> None:
    import robotd.formats.record

    monkeypatch.setattr(robotd.formats.record, "FORMAT_VERSION", 3)
    write(tmp_path / "new.mcap", session(rng, 1))
    monkeypatch.undo()
    with pytest.raises(PersistenceError, match=r"new.mcap: recording format version 3; this robotd reads versions "
                                               r"1, 2: a newer robotd wrote it"):  # fmt: skip
        SessionReader(tmp_path / "new.mcap")


def small_chunks(path: Path, rng: np.random.Generator, n: int = 20) -> list[StereoFrame]:
    """A recording of ``n`` frames in many small chunks; returns the frames."""
    events = session(rng, n)
    write(path, events, chunk_size=8 * 1024)
    return [e for e in events if isinstance(e, StereoFrame)]


def test_a_truncated_file_reads_up_to_the_damage_and_says_where(tmp_path: Path, rng: np.random.Generator) -> None:
    path = tmp_path / "s.mcap"
    frames = small_chunks(path, rng)
    data = path.read_bytes()
    # the last 100 bytes missing (summary and footer): every frame is still there
    cut = tmp_path / "cut100.mcap"
    cut.write_bytes(data[:-100])
    r = SessionReader(cut)
    got = list(r.frames())
    assert len(got) == len(frames)
    assert not r.finished and r.stopped is not None and f"of {len(data) - 100}" in r.stopped
    # cut in the middle of the data: the frames of the whole chunks before the cut, bit-identical
    half = tmp_path / "half.mcap"
    half.write_bytes(data[: len(data) // 2])
    r = SessionReader(half)
    got = list(r.frames())
    assert 0 < len(got) < len(frames)
    for a, b in zip(frames, got):
        assert_same(a, b)
    truncated = r"stopped at byte \d+ of \d+: Chunk record of \d+ bytes, only \d+ left in the file \(truncated\)"
    assert re.search(truncated, r.stopped or "")
    with pytest.raises(PersistenceError, match=r"half.mcap: stopped at byte"):
        list(SessionReader(half, strict=True).frames())


def test_a_recorder_that_was_killed_leaves_a_replayable_file_kept_by_the_next_one(
    tmp_path: Path, rng: np.random.Generator
) -> None:
    path = tmp_path / "s.mcap"
    events = session(rng, 12)
    w = SessionWriter(path, MODEL, {}, flush_period_s=0.0)  # every message's chunk goes to the OS at once
    for e in events[:-3]:  # ... and then the process dies: no close, no summary
        put(w, e)
    assert not path.exists() and w.tmp_path.stat().st_size > 0
    r = SessionReader(w.tmp_path)
    assert len(list(r.frames())) == 11 and not r.finished
    assert "the file ends without its DataEnd/Footer (not closed cleanly)" in (r.stopped or "")
    # the next recorder to the same path keeps it instead of overwriting it
    w2 = SessionWriter(path, MODEL, {})
    kept = w2.kept_interrupted
    assert kept is not None and kept.name.startswith("s.interrupted-") and kept.suffix == ".mcap"
    w2.discard()
    assert len(list(SessionReader(kept).frames())) == 11
    with open_camera(str(kept)) as cam:
        assert len(list(cam.frames())) == 11


def _forged_png(img: np.ndarray, level: int) -> bytes:
    """A valid PNG of ``img`` whose header (with a valid CRC) claims 30000×30000 pixels."""
    import struct
    import zlib

    png = bytearray(cv2.imencode(".png", img)[1].tobytes())
    struct.pack_into(">II", png, 16, 30000, 30000)
    struct.pack_into(">I", png, 29, zlib.crc32(bytes(png[12:29])))
    return bytes(png)


@pytest.mark.parametrize("damage", ["junk", "header only", "forged PNG header", "newer format"])
def test_a_bad_file_ends_replay_in_one_line_with_exit_2(
    damage: str, tmp_path: Path, rng: np.random.Generator, monkeypatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import robotd.formats.record
    from robotd.tools.cli import main

    path = tmp_path / "bad.mcap"
    if damage == "junk":
        path.write_bytes(b"\x89MCAP0\r\n" + bytes(rng.integers(0, 256, 5000, dtype=np.uint8)))
    elif damage == "header only":
        write(path, session(rng, 4))
        path.write_bytes(path.read_bytes()[:600])
    else:
        with monkeypatch.context() as m:
            if damage == "forged PNG header":
                m.setattr(robotd.formats.record, "encode_png", _forged_png)
            else:
                m.setattr(robotd.formats.record, "FORMAT_VERSION", 7)
            write(path, session(rng, 4))
    assert main(["replay", str(path), "--quiet", "--log-level", "WARNING"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"robotd: error: {path}"), err
    if damage == "forged PNG header":
        assert "no frame was processed: stopped at byte" in err[0] and "PNG header says 30000x30000" in err[0]


def test_the_ellipsoids_are_capped_to_the_newest_landmarks(tmp_path: Path, rng: np.random.Generator) -> None:
    from robotd.core.msgs import LandmarkMap

    path = tmp_path / "s.mcap"
    lm = LandmarkMap(np.arange(5, dtype=np.int64), np.arange(15, dtype=float).reshape(5, 3), np.stack([np.eye(3)] * 5))
    with SessionWriter(path, MODEL, {}, max_ellipsoids=2) as w:
        w.write_frame(next(e for e in session(rng, 1) if isinstance(e, StereoFrame)))
        w.write_map(T0, w.map_messages(T0, lm))  # built outside the writer's lock, as the recorder does
    msgs = decode_all(path)
    assert len(np.frombuffer(msgs["/robotd/map"][0][1].data, np.uint8)) == 5 * 16  # every landmark in the cloud
    spheres = msgs["/robotd/map_covariance"][0][1].entities[0].spheres
    assert [s.pose.position.x for s in spheres] == [9.0, 12.0]  # ... the ellipsoids of the two newest
