"""KITTI raw OXTS records as vehicle odometry (drivers/kitti_oxts.py, issue 13 item 5): parsing and
its errors, the IMU -> robot frame rotation with the lever arm, stamps on the image clock, the
kitti vehicle's odometry=oxts option, and on the real drive: dead reckoning against truth and a
replay that uses it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.dataset import open_kitti_vehicle
from drivers.kitti_oxts import (
    OXTS_SIGMA_RATE_RADPS,
    OXTS_SIGMA_VEL_MPS,
    find_oxts,
    kitti_oxts_odometry,
    read_oxts,
    read_timestamps_ns,
)
from robotd.config import ReplayConfig
from robotd.core.errors import DatasetError, DriverError
from robotd.core.geometry import rot_x, rot_y, rot_z
from tests.drivers.test_dataset_kitti import B, make_kitti
from tests.support.tolerances import CONDITIONED_ATOL

# Calibration of the synthetic drive, chosen so the IMU -> robot map is known by hand: the IMU
# sits at IMU_IN_VELO (Velodyne coordinates, axes shared: x forward, y left, z up), the camera at
# the Velodyne origin looking forward (optical: x right, y down, z forward), R_rect_00 = I.
IMU_IN_VELO = np.array([0.5, 0.2, -0.3])
# so the robot origin (baseline centre, b/2 right of the left camera: velo (0, -b/2, 0)) is, in
# IMU coordinates, r = (0, -b/2, 0) - IMU_IN_VELO, and FLU -> FRD flips y and z
R_IN_IMU = np.array([0.0, -B / 2.0, 0.0]) - IMU_IN_VELO
FLU_TO_FRD = np.diag([1.0, -1.0, -1.0])
IMAGE_T0 = "2011-09-26 13:08:24.973999360"  # the first image stamp: 0 on the image clock
OXTS_OFFSETS_NS = np.array([-4_494_184, 1_699_890, -1_583_370, 4_000_000, 2_000_000, 0])  # oxts − image, as logged


def _stamp(base_s: int, ns: int) -> str:
    """'2011-09-26 13:08:SS.fffffffff' for base + ns after 13:08:00."""
    total = base_s * 1_000_000_000 + ns
    s, f = divmod(total, 1_000_000_000)
    return f"2011-09-26 13:08:{s:02d}.{f:09d}"


def make_raw(root: Path, n: int = 6, drive: str = "2011_01_01_drive_0042_sync") -> dict[str, np.ndarray]:
    """A KITTI folder (make_kitti) keeping a raw drive with n OXTS records: a body velocity and
    rate known in the IMU frame, under a tilted attitude. Returns the truth of the records."""
    make_kitti(root, n=n, times=False, poses=False)
    raw = root / "raw"
    d = raw / drive
    (d / "oxts" / "data").mkdir(parents=True)
    (d / "image_00").mkdir()
    img_ns = 24_973_999_360 + np.arange(n) * 103_500_000  # ~9.66 Hz, as the real drive
    (d / "image_00" / "timestamps.txt").write_text("".join(_stamp(0, int(t)) + "\n" for t in img_ns))
    (root / "times.txt").write_text("".join(f"{(t - img_ns[0]) / 1e9:.6e}\n" for t in img_ns))
    oxts_ns = img_ns + OXTS_OFFSETS_NS[:n]
    (d / "oxts" / "timestamps.txt").write_text("".join(_stamp(0, int(t)) + "\n" for t in oxts_ns))
    rng = np.random.default_rng(7)
    rpy = np.column_stack([rng.normal(0, 0.1, n), rng.normal(0, 0.05, n), rng.uniform(-3, 3, n)])
    v_imu = np.column_stack([rng.uniform(5, 12, n), rng.normal(0, 0.3, n), rng.normal(0, 0.1, n)])
    w_imu = rng.normal(0, 0.2, (n, 3))
    R = rot_z(rpy[:, 2]) @ rot_y(rpy[:, 1]) @ rot_x(rpy[:, 0])
    v_enu = np.einsum("nij,nj->ni", R, v_imu)
    for i in range(n):
        row = np.zeros(30)
        row[:3] = (49.0, 8.4, 110.0)
        row[3:6] = rpy[i]
        row[6], row[7], row[10] = v_enu[i, 1], v_enu[i, 0], v_enu[i, 2]  # vn, ve, vu
        row[8], row[9] = 999.0, -999.0  # vf, vl: not used (vl's sign is not what dataformat.txt says)
        row[17:20] = w_imu[i]  # wx, wy, wz
        row[20:23] = 555.0  # wf, wl, wu: not used
        (d / "oxts" / "data" / f"{i:010d}.txt").write_text(" ".join(f"{x:.15g}" for x in row) + "\n")
    (raw / "calib_imu_to_velo.txt").write_text(
        "calib_time: x\nR: 1 0 0 0 1 0 0 0 1\nT: " + " ".join(map(str, IMU_IN_VELO)) + "\n"
    )
    # velodyne (x fwd, y left, z up) -> camera optical: x_c = -y_v, y_c = -z_v, z_c = x_v
    (raw / "calib_velo_to_cam.txt").write_text("calib_time: x\nR: 0 -1 0 0 0 -1 1 0 0\nT: 0 0 0\n")
    (raw / "calib_cam_to_cam.txt").write_text("calib_time: x\nR_rect_00: 1 0 0 0 1 0 0 0 1\n")
    return {"img_ns": img_ns, "oxts_ns": oxts_ns, "v_imu": v_imu, "w_imu": w_imu}


def test_records_become_robot_frame_velocities_with_the_lever_arm(tmp_path: Path) -> None:
    truth = make_raw(tmp_path / "seq")
    samples = kitti_oxts_odometry(tmp_path / "seq", B)
    assert samples is not None and len(samples) == 6
    v = np.array([s.vel_R_mps for s in samples])
    w = np.array([s.rate_R_radps for s in samples])
    # by hand: the velocity at the robot origin v + ω × r (IMU frame), then FLU -> FRD
    expect_v = (truth["v_imu"] + np.cross(truth["w_imu"], R_IN_IMU)) @ FLU_TO_FRD.T
    np.testing.assert_allclose(v, expect_v, atol=CONDITIONED_ATOL)
    np.testing.assert_allclose(w, truth["w_imu"] @ FLU_TO_FRD.T, atol=CONDITIONED_ATOL)
    assert all(s.source == "oxts" for s in samples)
    np.testing.assert_allclose(
        samples[0].cov, np.diag([OXTS_SIGMA_VEL_MPS**2] * 3 + [OXTS_SIGMA_RATE_RADPS**2] * 3), rtol=1e-15
    )


def test_records_are_stamped_on_the_image_clock(tmp_path: Path) -> None:
    truth = make_raw(tmp_path / "seq")
    samples = kitti_oxts_odometry(tmp_path / "seq", B)
    assert samples is not None
    # a record's stamp minus the first image stamp, to the nanosecond: the clock of times.txt
    assert [s.t_ns for s in samples] == (truth["oxts_ns"] - truth["img_ns"][0]).tolist()
    assert samples[0].t_ns == -4_494_184  # a record just before the first frame
    # frames on another clock than image_00/timestamps.txt (a times.txt at 10 Hz, or none: 0.1 s ×
    # index) would misplace every record against them
    for times in (True, False):
        if times:
            (tmp_path / "seq" / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(6)))
        else:
            (tmp_path / "seq" / "times.txt").unlink()
        with pytest.raises(DatasetError, match=r"frames' stamps .* differ from .*image_00/timestamps\.txt"):
            open_kitti_vehicle(f"kitti://{tmp_path / 'seq'}?odometry=oxts")


def test_timestamps_parse_to_integer_nanoseconds(tmp_path: Path) -> None:
    p = tmp_path / "timestamps.txt"
    p.write_text(f"{IMAGE_T0}\n2011-09-26 13:08:25.077800192\n\n2011-09-26 13:08:25.5\n")
    t = read_timestamps_ns(p)
    assert (t - t[0]).tolist() == [0, 103_800_832, 526_000_640]
    p.write_text("2011-09-26 13:08:25,0778\n")
    with pytest.raises(DatasetError, match=r"timestamps\.txt:1: expected 'YYYY-MM-DD HH:MM:SS\.fffffffff'"):
        read_timestamps_ns(p)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda s: " ".join(s.split()[:23]), r"0000000003\.txt: expected one line of 30 numbers .*got 23 numbers"),
        (lambda s: s.replace(s.split()[5], "x1.5", 1), r"0000000003\.txt: expected 30 numbers, got '"),
        (lambda s: s + s, r"0000000003\.txt: expected one line of 30 numbers .*got 2 lines"),
        (lambda s: s.replace(s.split()[7], "nan", 1), r"0000000003\.txt: non-finite values"),
        (None, r"0000000003\.txt: missing OXTS record"),
    ],
)
def test_a_malformed_record_is_a_clear_error_naming_the_file(tmp_path: Path, damage, message) -> None:
    make_raw(tmp_path / "seq")
    rec = tmp_path / "seq" / "raw" / "2011_01_01_drive_0042_sync" / "oxts" / "data" / "0000000003.txt"
    if damage is None:
        rec.unlink()
    else:
        rec.write_text(damage(rec.read_text()) + "\n")
    with pytest.raises(DatasetError, match=message):
        read_oxts(rec.parent.parent)


def test_missing_calibration_and_no_raw_folder(tmp_path: Path) -> None:
    make_raw(tmp_path / "seq")
    (tmp_path / "seq" / "raw" / "calib_velo_to_cam.txt").unlink()
    with pytest.raises(DatasetError, match=r"calib_velo_to_cam\.txt: no such file"):
        kitti_oxts_odometry(tmp_path / "seq", B)
    plain = make_kitti(tmp_path / "plain")
    assert find_oxts(plain) is None and kitti_oxts_odometry(plain, B) is None


def test_kitti_vehicle_offers_the_records_cut_to_the_selected_frames(tmp_path: Path) -> None:
    root = tmp_path / "seq"
    truth = make_raw(root)
    with open_kitti_vehicle(f"kitti://{root}?odometry=oxts") as veh:
        assert veh.odometry_source == "oxts"
        assert len(list(veh.odometry())) == 6
    # frames 2..3: one record at or before the first (t − 1.58 ms at frame 2) to one at or after the last
    with open_kitti_vehicle(f"kitti://{root}?start=2&stop=4&odometry=oxts&oxts_sigma_vel_mps=0.5") as veh:
        t = [s.t_ns for s in veh.samples]
        assert t == (truth["oxts_ns"][2:4] - truth["img_ns"][0]).tolist()
        assert veh.samples[0].cov is not None and veh.samples[0].cov[0, 0] == pytest.approx(0.25)
    # frames 1..2: frame 1's record comes after it (so from record 0), frame 2's before it (to record 3)
    with open_kitti_vehicle(f"kitti://{root}?start=1&stop=3&odometry=oxts") as veh:
        assert [s.t_ns for s in veh.samples] == (truth["oxts_ns"][0:4] - truth["img_ns"][0]).tolist()
    # the default, and a folder without raw records: no odometry at all
    assert open_kitti_vehicle(f"kitti://{root}").odometry_source == "none"
    assert open_kitti_vehicle(f"kitti://{make_kitti(tmp_path / 'plain')}?odometry=oxts").odometry_source == "none"
    with pytest.raises(DriverError, match=r"option odometry: expected one of \['none', 'oxts'\], got 'gps'"):
        open_kitti_vehicle(f"kitti://{root}?odometry=gps")
    with pytest.raises(DriverError, match="odometry=oxts and gt_odometry both given"):
        open_kitti_vehicle(f"kitti://{root}?odometry=oxts&gt_odometry=1")


def test_config_defaults_are_the_drivers_stated_noise() -> None:
    r = ReplayConfig()
    assert (r.oxts_sigma_vel_mps, r.oxts_sigma_rate_radps) == (OXTS_SIGMA_VEL_MPS, OXTS_SIGMA_RATE_RADPS)
    assert r.odometry == "none", "vision only stays the default until the lead decides"


# --------------------------------------------------------------------------------------------
# the real drive: kitti-raw-0009 keeps the OXTS records of all 447 frames

# Dead reckoning over the 51 imaged frames measured drift 1.38 %, ATE 0.108 m, RPE 0.12°/frame
# against the folder's truth (which comes from the same unit's GPS positions and INS attitude: the
# remaining error is the GPS track differing from the velocity's direction by ~0.6°, and the 10 Hz
# hold of the rates). The bounds keep ~2× margin and catch a wrong attitude or sign (the level-frame
# velocities without roll and pitch give 3.35 %, vf/vl with vl leftward as documented 3.2 %); the
# lever arm (0.4 cm on this straight piece) is the synthetic test's.
DR_MAX_DRIFT_PCT = 2.5
DR_MAX_ATE_M = 0.2
DR_MAX_RPE_ROT_DEG = 0.25


def test_oxts_dead_reckoning_follows_the_truth_of_kitti_raw_0009(shared_data) -> None:
    from drivers.dataset import KittiCamera
    from robotd.pipeline.odometry import OdometryGate, dead_reckon
    from robotd.research.evaluate import Trajectory, evaluate_trajectories

    root = shared_data("kitti-raw-0009", "raw")
    veh = open_kitti_vehicle(f"kitti://{root.parent}?odometry=oxts")
    truth = KittiCamera(f"kitti://{root.parent}").truth()
    gate = OdometryGate()  # the daemon's default limits take a car at ~10.5 m/s
    assert all(gate.accept(s) for s in veh.samples), gate.rejected
    t = np.array([t for t, _ in truth])
    assert veh.samples[0].t_ns <= t[0] and veh.samples[-1].t_ns >= t[-1]
    P = dead_reckon(veh.samples, t)
    m = evaluate_trajectories(Trajectory(t / 1e9, P), Trajectory(t / 1e9, np.stack([g for _, g in truth])))
    assert m["frames"] == 51
    assert m["drift_pct"] < DR_MAX_DRIFT_PCT and m["ate_rmse_m"] < DR_MAX_ATE_M, m
    assert m["rpe_rot_deg"] < DR_MAX_RPE_ROT_DEG, m


@pytest.fixture(scope="module")
def oxts_replay() -> dict:
    from robotd.config import load_config
    from robotd.tools.replay import replay
    from tests.conftest import data_path

    root = data_path("kitti-raw-0009")
    cfg = load_config(overrides={"replay": {"odometry": "dataset"}})
    return replay(cfg, f"kitti://{root}", progress=False)


def test_replay_with_the_recorded_odometry(oxts_replay: dict) -> None:
    s = oxts_replay
    assert s["odometry"] == "oxts" and s["frames"] == 51
    assert s["odometry_priors"] == 50 and s["visual_priors"] == 0 and s["odometry_rejected"] == 0
    assert s["truth_ate_rmse_m"] < 0.3  # measured 0.135 m (vision only 0.120 m)


def test_replay_with_the_recorded_odometry_loses_no_frame(oxts_replay: dict) -> None:
    assert oxts_replay["lost_frames"] == 0
