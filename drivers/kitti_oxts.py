"""KITTI raw OXTS (GPS/INS) records as the vehicle odometry of a KITTI folder.

A KITTI raw drive keeps, per frame, one line of 30 numbers from the car's OXTS RT3003 GPS/INS
(``<date>/<drive>_sync/oxts/data/NNNNNNNNNN.txt``, fields in ``oxts/dataformat.txt``) and its time
in ``oxts/timestamps.txt``; the calibration chain IMU -> Velodyne -> camera 0 -> rectified camera 0
is in ``<date>/calib_imu_to_velo.txt``, ``calib_velo_to_cam.txt`` and ``calib_cam_to_cam.txt``.
A KITTI odometry-layout folder made from such a drive may keep the raw drive under ``raw/``
(``raw/<drive>/oxts`` with the calibration files in ``raw/``); :func:`find_oxts` finds it there,
whatever the drive's name.

The records become :class:`robotd.core.msgs.Odometry` samples as a rover's wheel odometry would
arrive: the body velocity and rates of the robot frame (FRD at the stereo baseline centre of the
rectified rig), stamped on the image clock (a frame's ``times.txt`` stamp is its
``image_00/timestamps.txt`` stamp minus the first one; an OXTS record gets its own stamp minus
that same first image stamp), with a stated noise carried as the samples' covariance.

Which fields (checked on drive 2011_09_26_0009, all 447 records):

- **Rates**: ``wx, wy, wz`` (IMU frame: x forward, y left, z up). ``wf, wl, wu`` are the same
  vector in the level heading frame (they equal R_y(pitch) R_x(roll) (wx, wy, wz) to 8e-4 rad/s)
  and ``wu`` integrates to the change of ``yaw`` (slope 0.997).
- **Velocity**: the navigation-frame ``ve, vn`` (east, north) and ``vu`` (up), rotated into the
  IMU frame by the record's attitude, v_imu = (R_z(yaw) R_y(pitch) R_x(roll))ᵀ (ve, vn, vu): the
  devkit's attitude convention, the one the folder's ``poses.txt`` was made with. ``vf`` agrees
  with that to 6 mm/s; ``vl``, documented as leftward, has the opposite sign (correlation −0.96
  with the leftward velocity from ``ve, vn`` and ``yaw``: the RT3003's own lateral output points
  right), so it is not used.
- **Lever arm**: the robot origin sits r = (1.08, −0.58, 0.73) m from the IMU (IMU frame); the
  velocity there is v + ω × r. On this drive's 51 imaged frames |ω × r| ≤ 0.055 m/s, in its turns
  (25°/s) up to 0.56 m/s.
"""

from __future__ import annotations

import calendar
import logging
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robotd.core.errors import DatasetError
from robotd.core.geometry import R_ROBOT_OPTICAL, rot_x, rot_y, rot_z, se3, se3_inverse
from robotd.core.msgs import Odometry

logger = logging.getLogger(__name__)

OXTS_FIELDS = 30  # numbers per record line (oxts/dataformat.txt)
# columns of a record (oxts/dataformat.txt)
_ROLL, _PITCH, _YAW = 3, 4, 5
_VN, _VE, _VU = 6, 7, 10
_WX, _WY, _WZ = 17, 18, 19

# Noise of one OXTS sample (per axis, 1σ), stated as the samples' covariance. Velocity: the unit's
# own velocity-accuracy field (vel_accuracy, column 24) reads 0.06 m/s on this drive (it ran
# without RTK: pos_accuracy 0.46 m), 8× the sample-to-sample jitter (second differences: 0.007 m/s)
# and 4× the RT3003 data sheet's 0.05 km/h RMS, which assumes differential corrections. Rates: the
# data sheet's gyro bias (0.01°/s) is negligible; what a 10 Hz zero-order hold misses is the body's
# vibration between samples: over one frame the integrated rates differ from the INS's own attitude
# change by 0.087°/0.082°/0.020° RMS (roll/pitch/yaw), i.e. 0.015 rad/s over 0.1 s (yaw ~4× better).
OXTS_SIGMA_VEL_MPS = 0.06
OXTS_SIGMA_RATE_RADPS = 0.015

_STAMP = re.compile(r"^(\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2})(?:\.(\d{1,9}))?$")


@dataclass(frozen=True, slots=True, eq=False)
class OxtsRecords:
    """The OXTS records of one drive that robotd uses (N records, in file order)."""

    t_ns: np.ndarray  # (N,) int64 stamps as logged [ns since the epoch, logging PC clock]
    rpy_rad: np.ndarray  # (N, 3) roll, pitch, yaw (devkit convention: R = R_z(yaw) R_y(pitch) R_x(roll))
    vel_enu_mps: np.ndarray  # (N, 3) east, north, up
    rate_imu_radps: np.ndarray  # (N, 3) wx, wy, wz in the IMU frame (x forward, y left, z up)


def find_oxts(root: Path) -> Path | None:
    """The ``oxts/`` folder of the raw drive kept inside a KITTI folder (``raw/*/oxts``), or None.

    Raises DatasetError when there are several (which drive's odometry would be ambiguous)."""
    found = sorted(p for p in root.glob("raw/*/oxts") if (p / "data").is_dir())
    if len(found) > 1:
        raise DatasetError(f"{root}: several raw OXTS folders {[str(p) for p in found]}; expected one drive")
    return found[0] if found else None


def read_timestamps_ns(path: Path) -> np.ndarray:
    """A KITTI raw ``timestamps.txt`` (``YYYY-MM-DD HH:MM:SS.fffffffff`` per line) -> (N,) int64 ns.

    Parsed as integers (a float holds only ~0.2 µs at 1.3e9 s); the date is taken as UTC, which
    does not matter: only differences between stamps of the same file set are used."""
    if not path.is_file():
        raise DatasetError(f"{path}: no such file (KITTI raw timestamps)")
    out: list[int] = []
    for k, line in enumerate(path.read_text().splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        m = _STAMP.match(s)
        if m is None:
            raise DatasetError(f"{path}:{k}: expected 'YYYY-MM-DD HH:MM:SS.fffffffff', got {s!r}")
        whole = calendar.timegm(time.strptime(m.group(1), "%Y-%m-%d %H:%M:%S"))
        out.append(whole * 1_000_000_000 + int((m.group(2) or "0").ljust(9, "0")))
    if not out:
        raise DatasetError(f"{path}: no timestamps")
    return np.array(out, dtype=np.int64)


def read_oxts(oxts_dir: Path) -> OxtsRecords:
    """Read ``oxts/timestamps.txt`` and one ``data/NNNNNNNNNN.txt`` per stamp.

    A missing record, or one that is not a single line of 30 finite numbers, is a DatasetError
    naming the file."""
    t_ns = read_timestamps_ns(oxts_dir / "timestamps.txt")
    if np.any(np.diff(t_ns) <= 0):
        raise DatasetError(f"{oxts_dir / 'timestamps.txt'}: stamps are not strictly increasing")
    rows = np.empty((t_ns.size, OXTS_FIELDS))
    for i in range(t_ns.size):
        rows[i] = _read_record(oxts_dir / "data" / f"{i:010d}.txt")
    return OxtsRecords(
        t_ns=t_ns,
        rpy_rad=rows[:, [_ROLL, _PITCH, _YAW]],
        vel_enu_mps=rows[:, [_VE, _VN, _VU]],
        rate_imu_radps=rows[:, [_WX, _WY, _WZ]],
    )


def _read_record(path: Path) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: missing OXTS record (one per line of oxts/timestamps.txt)")
    lines = [s for s in path.read_text().splitlines() if s.strip()]
    parts = lines[0].split() if len(lines) == 1 else []
    if len(parts) != OXTS_FIELDS:
        got = f"{len(lines)} lines" if len(lines) != 1 else f"{len(parts)} numbers"
        raise DatasetError(f"{path}: expected one line of {OXTS_FIELDS} numbers (oxts/dataformat.txt), got {got}")
    try:
        row = np.array([float(p) for p in parts])
    except ValueError:
        raise DatasetError(f"{path}: expected {OXTS_FIELDS} numbers, got {lines[0].strip()!r}") from None
    if not np.all(np.isfinite(row)):
        raise DatasetError(f"{path}: non-finite values")
    return row


def _calib_rows(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise DatasetError(f"{path}: no such file (KITTI raw calibration, beside the drive folder)")
    rows: dict[str, np.ndarray] = {}
    for line in path.read_text().splitlines():
        key, sep, rest = line.partition(":")
        if sep and key.strip() in keys:
            try:
                rows[key.strip()] = np.array(rest.split(), dtype=float)
            except ValueError:
                raise DatasetError(f"{path}: row {key.strip()!r} is not numbers") from None
    want = {"R": 9, "T": 3, "R_rect_00": 9}
    bad = [k for k in keys if k not in rows or rows[k].size != want[k]]
    if bad:
        raise DatasetError(f"{path}: expected rows {', '.join(f'{k}: ({want[k]} numbers)' for k in keys)}; bad {bad}")
    return rows


def T_rect0_imu(date_dir: Path) -> np.ndarray:
    """(4, 4) IMU -> rectified camera 0: R_rect_00 · T_cam0_velo · T_velo_imu (the devkit's chain)."""
    iv = _calib_rows(date_dir / "calib_imu_to_velo.txt", ("R", "T"))
    vc = _calib_rows(date_dir / "calib_velo_to_cam.txt", ("R", "T"))
    cc = _calib_rows(date_dir / "calib_cam_to_cam.txt", ("R_rect_00",))
    T_velo_imu = se3(iv["R"].reshape(3, 3), iv["T"])
    T_cam0_velo = se3(vc["R"].reshape(3, 3), vc["T"])
    R0 = se3(cc["R_rect_00"].reshape(3, 3), np.zeros(3))
    return R0 @ T_cam0_velo @ T_velo_imu  # type: ignore[no-any-return]


def T_robot_imu(T_rect0_imu: np.ndarray, baseline_m: float) -> np.ndarray:
    """(4, 4) IMU -> robot frame: FRD axes, origin at the baseline centre, b/2 to the right of the
    rectified left camera (the frame of ``drivers.dataset.kitti_truth_to_robot``)."""
    T_R_C = se3(R_ROBOT_OPTICAL, -R_ROBOT_OPTICAL @ np.array([baseline_m / 2.0, 0.0, 0.0]))
    return T_R_C @ T_rect0_imu  # type: ignore[no-any-return]


def oxts_body_motion(rec: OxtsRecords, T_R_imu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vel_R (N, 3) [m/s], rate_R (N, 3) [rad/s]) of the robot origin, in the robot frame.

    v_imu = R_world_imuᵀ v_enu (attitude of the same record); at the robot origin, r = the origin
    in IMU coordinates, v = v_imu + ω × r; both rotated by R_robot_imu."""
    roll, pitch, yaw = rec.rpy_rad.T
    R_w_imu = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)  # (N, 3, 3)
    v_imu = np.einsum("nji,nj->ni", R_w_imu, rec.vel_enu_mps)
    r = se3_inverse(T_R_imu)[:3, 3]
    v_origin = v_imu + np.cross(rec.rate_imu_radps, r)
    R = T_R_imu[:3, :3]
    return v_origin @ R.T, rec.rate_imu_radps @ R.T


def odometry_cov(sigma_vel_mps: float, sigma_rate_radps: float) -> np.ndarray:
    """(6, 6) diagonal sample covariance over (vel, rate)."""
    return np.diag([sigma_vel_mps**2] * 3 + [sigma_rate_radps**2] * 3)


# a frame's stamp (times.txt: seconds with 7 significant digits) and its image_00 stamp minus the
# first may differ by round-off (≤ 10 µs); a different clock differs by tens of ms within seconds
FRAME_CLOCK_TOL_NS = 1_000_000


def kitti_oxts_odometry(
    root: Path,
    baseline_m: float,
    sigma_vel_mps: float = OXTS_SIGMA_VEL_MPS,
    sigma_rate_radps: float = OXTS_SIGMA_RATE_RADPS,
    frames: Sequence[tuple[int, int]] = (),
) -> list[Odometry] | None:
    """The OXTS records of the raw drive inside KITTI folder ``root`` as robot-frame Odometry on
    the image clock (module docstring), ``source="oxts"``; None when the folder has no raw OXTS.

    ``frames``: (index, t_ns) of the folder's frames as the replay stamps them (from times.txt);
    a DatasetError when they are not that image clock (within 1 ms), since every record would
    then be misplaced against the frames."""
    oxts = find_oxts(root)
    if oxts is None:
        return None
    drive = oxts.parent
    rec = read_oxts(oxts)
    image_stamps = drive / "image_00" / "timestamps.txt"
    t_img = read_timestamps_ns(image_stamps)
    idx = np.array([i for i, _ in frames if 0 <= i < t_img.size], dtype=np.int64)
    if idx.size:
        t_frames = np.array([t for i, t in frames if 0 <= i < t_img.size], dtype=np.int64)
        off = np.abs(t_frames - (t_img[idx] - t_img[0]))
        if off.max() > FRAME_CLOCK_TOL_NS:
            raise DatasetError(
                f"{root}: the frames' stamps (times.txt, or 0.1 s × index without it) differ from {image_stamps} "
                f"minus its first stamp by up to {off.max() / 1e6:.1f} ms: the OXTS records would be on another clock"
            )
    vel, rate = oxts_body_motion(rec, T_robot_imu(T_rect0_imu(drive.parent), baseline_m))
    cov = odometry_cov(sigma_vel_mps, sigma_rate_radps)
    cov.flags.writeable = False  # shared by every sample
    t = rec.t_ns - t_img[0]
    logger.info(
        "%s: %d OXTS records as odometry (image clock, %+.1f…%+.1f s), sigma %.3g m/s, %.3g rad/s",
        oxts,
        t.size,
        t[0] / 1e9,
        t[-1] / 1e9,
        sigma_vel_mps,
        sigma_rate_radps,
    )
    return [Odometry(int(t[i]), vel[i], rate[i], source="oxts", cov=cov) for i in range(t.size)]
