"""OAK driver without a device: the REAL depthai Sync node in host-only pipelines, fed real
dai.ImgFrame messages by a ThreadedHostNode; pairing, drops, gaps, stamps, reconnect, calibration."""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import numpy as np
import pytest

dai = pytest.importorskip("depthai")

from drivers.oak.camera import (  # noqa: E402
    OakCamera,
    OakOptions,
    PairGate,
    calibration_from_handler,
    make_sync,
    timedelta_ns,
)
from robotd.core.errors import DriverError  # noqa: E402
from tests.support.tolerances import CONDITIONED_ATOL, CONDITIONED_RTOL, FLOAT32_ROUNDING_TOL  # noqa: E402

# the README quotes the factory translation to 0.001 cm (1e-5 m)
README_T_ATOL_M = 2e-5
PERIOD = 1 / 30
EXPOSURE_US = 8000


@dataclass
class Shot:
    """One scripted stereo capture: end-of-exposure stamps (s, dai.Clock), sequence numbers."""

    t_left: float
    t_right: float
    seq_left: int
    seq_right: int
    send_right: bool = True


def script(n: int, t0: float, offset: dict[int, float] | None = None, skip: set[int] | None = None) -> list[Shot]:
    """n pairs at 30 fps; right lags by 0.2 ms; ``offset`` moves chosen right frames; ``skip`` drops seq numbers."""
    offset, skip = offset or {}, skip or set()
    shots, seq = [], 0
    for i in range(n):
        while seq in skip:
            seq += 1
        t = t0 + i * PERIOD
        shots.append(Shot(t, t + 0.0002 + offset.get(i, 0.0), seq, seq))
        seq += 1
    return shots


class ScriptedStereo(dai.node.ThreadedHostNode):
    """Emits real GRAY8 ImgFrames with stamps, exposure and sequence numbers, like two mono cameras."""

    def __init__(self) -> None:
        super().__init__()
        self.left = self.createOutput()
        self.right = self.createOutput()
        self.shots: list[Shot] = []
        self.done = threading.Event()

    def _frame(self, value: int, t: float, seq: int) -> Any:
        f = dai.ImgFrame()
        f.setCvFrame(np.full((40, 64), value % 256, np.uint8), dai.ImgFrame.Type.GRAY8)
        f.setTimestamp(timedelta(seconds=t))
        f.setSequenceNum(seq)
        cam = f.cam
        cam.exposureTimeUs = EXPOSURE_US
        f.cam = cam
        return f

    def run(self) -> None:
        for s in self.shots:
            self.left.send(self._frame(s.seq_left, s.t_left, s.seq_left))
            if s.send_right:
                self.right.send(self._frame(s.seq_right, s.t_right, s.seq_right))
            time.sleep(0.002)
        self.done.set()


class HostSession:
    """A PipelineSession on a host-only pipeline: ScriptedStereo -> real Sync (on host) -> queue."""

    def __init__(self, opts: OakOptions, shots: list[Shot], fail_after: int | None = None) -> None:
        self._stack = contextlib.ExitStack()
        p = self._stack.enter_context(dai.Pipeline(False))
        self.pipeline = p
        self.source = p.create(ScriptedStereo)
        self.source.shots = shots
        sync, q = make_sync(p, opts, run_on_host=True)
        self.source.left.link(sync.inputs["left"])
        self.source.right.link(sync.inputs["right"])
        self.queue = FlakyQueue(q, fail_after) if fail_after is not None else q
        self.rectifier = None
        self.model = None
        self.rectified = False
        self.raw_calibration = None
        p.start()

    def is_running(self) -> bool:
        return bool(self.pipeline.isRunning())

    def close(self) -> None:
        self.pipeline.stop()
        self._stack.close()


class FlakyQueue:
    """Passes ``n`` groups through, then fails as a USB link does when the cable is pulled."""

    def __init__(self, q: Any, n: int) -> None:
        self.q, self.n = q, n

    def get(self, timeout: timedelta) -> Any:
        if self.n <= 0:
            raise RuntimeError("Communication exception - Couldn't read data from stream: 'sync' (X_LINK_ERROR)")
        self.n -= 1
        return self.q.get(timeout)


def collect(cam: OakCamera, n: int, deadline_s: float = 5.0) -> list[Any]:
    out: list[Any] = []
    timer = threading.Timer(deadline_s, cam.close)
    timer.start()
    try:
        for f in cam.frames(timeout_s=0.05):
            out.append(f)
            if len(out) >= n:
                break
    finally:
        timer.cancel()
    return out


def open_host(shots: list[Shot], **options: Any) -> OakCamera:
    cam = OakCamera("oak://", session_factory=lambda o: HostSession(o, shots), **options)
    cam.open()
    return cam


def test_pairs_come_out_with_exposure_middle_stamps() -> None:
    t0 = time.monotonic()
    shots = script(12, t0)
    cam = open_host(shots)
    frames = collect(cam, 12)
    cam.close()
    assert [f.seq for f in frames] == list(range(12))
    for f, s in zip(frames, shots):
        expected = timedelta_ns(timedelta(seconds=s.t_left)) - EXPOSURE_US * 500  # end - exposure/2
        assert f.t_ns == expected and isinstance(f.t_ns, int)
        assert f.exposure_ns == EXPOSURE_US * 1000  # the ImgFrame's own, for the blur model
        assert f.left[0, 0] == f.right[0, 0] == s.seq_left  # the two halves belong together
    st = cam.stats()
    assert st["mismatched"] == 0 and st["seq_missing"] == 0 and st["pairs"] == 12
    assert st["max_interval_us"] == 200


def test_offset_pair_is_dropped_and_counted() -> None:
    shots = script(12, time.monotonic(), offset={5: 0.012})  # 12 ms >> 5 ms threshold
    cam = open_host(shots)
    frames = collect(cam, 12, deadline_s=1.5)
    cam.close()
    seqs = [f.seq for f in frames]
    assert 5 not in seqs
    assert all(f.left[0, 0] == f.right[0, 0] == f.seq for f in frames)  # no mispaired halves come out
    st = cam.stats()
    # the late right frame makes Sync emit one mismatched group (left 6 with right 5); left 5 is lost
    assert st["mismatched"] >= 1
    # every capture is delivered or counted: nothing disappears silently
    assert st["pairs"] + st["mismatched"] + st["seq_missing"] == len(shots)
    for f in frames:  # stamps of delivered frames are the scripted ones
        assert f.t_ns == timedelta_ns(timedelta(seconds=shots[f.seq].t_left)) - EXPOSURE_US * 500


def test_sequence_gap_is_counted() -> None:
    shots = script(10, time.monotonic(), skip={4, 7, 8})
    cam = open_host(shots)
    frames = collect(cam, 10)
    cam.close()
    assert [f.seq for f in frames] == [0, 1, 2, 3, 5, 6, 9, 10, 11, 12]
    st = cam.stats()
    assert st["seq_missing"] == 3 and st["seq_gap_events"] == 2 and st["mismatched"] == 0


def test_reconnects_after_link_error_without_restart() -> None:
    t0 = time.monotonic()
    sessions: list[HostSession] = []

    def factory(o: OakOptions) -> HostSession:
        first = not sessions
        s = HostSession(o, script(6, t0 if first else t0 + 1.0), fail_after=3 if first else None)
        sessions.append(s)
        return s

    cam = OakCamera("oak://", session_factory=factory, reconnect_backoff_s=0.05)
    cam.open()
    frames = collect(cam, 9)
    st = cam.stats()
    cam.close()
    assert len(sessions) == 2
    assert len(frames) == 9  # 3 before the loss, 6 after
    assert st["link_errors"] == 1 and st["reconnects"] == 1 and st["degraded"] is False
    assert st["seq_resets"] == 1  # the reopened device restarts its sequence numbers
    assert np.all(np.diff([f.t_ns for f in frames]) > 0)


def test_no_device_fails_fast_or_degrades() -> None:
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK device is attached")
    t = time.monotonic()
    with pytest.raises(DriverError, match=r"oak://.*no OAK device"):
        OakCamera("oak://").open()
    assert time.monotonic() - t < 5.0  # never the 11 s of dai.Pipeline() without a device
    cam = OakCamera("oak://", wait_for_device=True, reconnect_backoff_s=0.05)
    cam.open()
    assert cam.stats()["degraded"] is True
    assert collect(cam, 1, deadline_s=0.5) == []
    assert cam.stats()["open_failures"] >= 1
    with pytest.raises(DriverError, match="no rectified model"):
        cam.rectified_model()


def test_options_are_validated() -> None:
    assert OakOptions.parse("oak://", {}).threshold_ns == 5_000_000
    assert OakOptions.parse("oak://?fps=60", {}).threshold_ns == 2_500_000  # 15 % of 16.7 ms
    with pytest.raises(DriverError, match="half the frame period"):
        OakOptions.parse("oak://", {"sync_threshold_ms": 20})
    with pytest.raises(DriverError, match="unknown option"):
        OakOptions.parse("oak://?exposure=1", {})
    with pytest.raises(DriverError, match="rectify"):
        OakOptions.parse("oak://", {"rectify": "gpu"})


def test_pair_gate_counts() -> None:
    g = PairGate(5_000_000)
    assert g.check(0, 100, 0) and g.check(33_000_000, 33_000_100, 1)
    assert not g.check(66_000_000, 72_000_000, 2)  # 6 ms apart
    assert g.check(133_000_000, 133_000_000, 4)  # seq 3 missing
    assert not g.check(100_000_000, 100_000_000, 5)  # time went backwards
    assert g.check(200_000_000, 200_000_000, 0)  # reset
    c = g.counts()
    assert (c["pairs"], c["mismatched"], c["seq_missing"], c["non_monotonic"], c["seq_resets"]) == (4, 1, 1, 1, 1)


def test_timedelta_ns_is_exact() -> None:
    td = timedelta(days=3, seconds=12345, microseconds=678901)
    assert timedelta_ns(td) == ((3 * 86400 + 12345) * 1_000_000 + 678901) * 1000


def test_factory_calibration_in_metres(shared_data) -> None:
    path = shared_data("oakd-calibration", "BW1098OBC_14442C10218CCCD200.json")
    cal = calibration_from_handler(dai.CalibrationHandler(str(path)), (640, 400))
    assert cal.K_left[0, 0] == pytest.approx(430.34, abs=0.01) and cal.K_left[1, 2] == pytest.approx(199.18, abs=0.01)
    np.testing.assert_allclose(cal.T, [-0.07550, -0.00117, 0.00050], atol=README_T_ATOL_M)  # cm -> m
    from drivers._rectify import Rectifier

    model = Rectifier(cal).model
    assert model.baseline_m == pytest.approx(0.0755, abs=2e-4)
    assert (model.width, model.height) == (640, 400) and 380 < model.f_px < 460


def test_driver_uses_the_oak_calibration_module_consistently(shared_data) -> None:
    from drivers.oak.camera import _load_calibration

    path = shared_data("oakd-calibration", "BW1098OBC_14442C10218CCCD200.json")
    handler = dai.CalibrationHandler(str(path))
    ours, used = calibration_from_handler(handler, (640, 400)), _load_calibration(handler, (640, 400))
    np.testing.assert_allclose(used.K_left, ours.K_left, rtol=CONDITIONED_RTOL)
    np.testing.assert_allclose(used.T, ours.T, atol=CONDITIONED_ATOL)  # both in metres
    # theirs re-orthonormalises the float32 EEPROM R, which moves entries by a few EPS32: FLOAT32_ROUNDING_TOL
    # (1e-7 before, which held with 3 % to spare: measured 9.65e-8)
    np.testing.assert_allclose(used.R, ours.R, atol=FLOAT32_ROUNDING_TOL)


# -- the user's calibration file (camera.calibration) -----------------------------------------------

OAK_JSON = ("oakd-calibration", "BW1098OBC_14442C10218CCCD200.json")


def _recalibrated(shared_data, tmp_path, size: tuple[int, int]) -> Any:
    """A calibration file as ``robotd-calib`` writes one for this OAK at ``size``: the factory rig
    (``import-oak``) recalibrated to a 10 % longer baseline and a principal point 1 px right,
    written and read back as the camchain YAML."""
    import dataclasses

    from calib.camchain import load_calibration, save_calibration
    from drivers.oak import load_oak_eeprom_json

    factory = load_oak_eeprom_json(shared_data(*OAK_JSON), *size)
    K = factory.K_left.copy()
    K[0, 2] += 1.0
    rig = dataclasses.replace(factory, K_left=K, T=factory.T * 1.1, source="recalibrated")
    return load_calibration(save_calibration(rig, tmp_path / "oak.yaml"))


def test_session_rig_takes_the_calibration_file_over_the_eeprom(shared_data, tmp_path) -> None:
    """The device's EEPROM read on the host (depthai's CalibrationHandler of the EEPROM JSON) is
    what a session rectifies with by default; with a calibration file, the file's rig instead."""
    from drivers.oak.camera import session_rig

    handler = dai.CalibrationHandler(str(shared_data(*OAK_JSON)))
    opts = OakOptions.parse("oak://", {})
    rectifier, factory, raw = session_rig(handler, opts, None)
    assert rectifier is not None and isinstance(raw, dict) and raw["boardName"] == "BW1098OBC"
    assert factory is not None and factory.baseline_m == pytest.approx(0.0755, abs=2e-4)
    user = _recalibrated(shared_data, tmp_path, (640, 400))
    cam = OakCamera("oak://", calibration=user)  # opens nothing until open()
    assert cam.calibration_rectifier is not None and cam.calibration_rectifier.calib is user
    rectifier, model, raw = session_rig(handler, cam.opts, cam.calibration_rectifier)
    assert rectifier is cam.calibration_rectifier and raw is user  # a recording keeps the file's rig
    assert model is not None and model.baseline_m == pytest.approx(1.1 * factory.baseline_m, rel=1e-3)
    # the factory rig is still what the device reports without a file, at any rectify mode
    for rectify in ("device", "none"):
        r, m, _ = session_rig(handler, OakOptions.parse("oak://", {"rectify": rectify}), None)
        assert r is None and (m is None) == (rectify == "none")


def test_open_camera_rectifies_with_the_calibration_file(shared_data, tmp_path, monkeypatch) -> None:
    """Through ``drivers.open_camera`` as the daemon opens it: the device session (the real depthai
    Sync on the host, the EEPROM from its JSON) gets the file's rectifier, every frame comes out
    rectified by it, and the rig the pipeline is built on is the file's."""
    import drivers
    import drivers.oak.camera as oak_camera

    user = _recalibrated(shared_data, tmp_path, (64, 40))  # the scripted frames are 64x40
    handler = dai.CalibrationHandler(str(shared_data(*OAK_JSON)))
    shots = script(6, time.monotonic())
    given: list[Any] = []

    def device_session(opts: OakOptions, device_id: str, user_rectifier: Any = None) -> HostSession:
        given.append(user_rectifier)
        s = HostSession(opts, shots)
        s.rectifier, s.model, s.raw_calibration = oak_camera.session_rig(handler, opts, user_rectifier)
        return s

    monkeypatch.setattr(oak_camera, "DeviceSession", device_session)
    cam = drivers.open_camera("oak://?width=64&height=40", calibration=user)
    with cam:
        frames = collect(cam, 6)
        model = cam.rectified_model()
    assert len(given) == 1 and given[0].calib is user
    assert model == given[0].model and model.baseline_m == pytest.approx(np.linalg.norm(user.T), rel=0.05)
    assert cam.raw_calibration is user
    assert len(frames) == 6 and all(f.rectified for f in frames)
    raw = np.full((40, 64), 3, np.uint8)
    assert np.array_equal(frames[3].left, given[0].rectify(raw, raw)[0])


@pytest.mark.parametrize(
    ("url", "size", "message"),
    [
        ("oak://", (1280, 800), r"for 1280x800 images but the camera gives 640x400; set \?width=1280&height=800"),
        ("oak://?rectify=device", (640, 400), r"rectify=host.*rectify=device the device rectifies from its EEPROM"),
        ("oak://?rectify=none", (640, 400), r"with rectify=none nothing rectifies"),
    ],
)
def test_a_calibration_file_the_oak_cannot_use_is_refused_before_any_device(
    shared_data, tmp_path, url: str, size: tuple[int, int], message: str
) -> None:
    import drivers
    from robotd.core.errors import CalibrationError

    user = _recalibrated(shared_data, tmp_path, size)
    with pytest.raises(CalibrationError, match=message):
        drivers.check_camera_url(url, calibration=user)
    with pytest.raises(CalibrationError, match=message):
        drivers.open_camera(url, calibration=user)
