"""UTIAS MRCLAM dataset loader (Leung et al., IJRR 2011): one robot's odometry and landmark observations.

Files (see the folder's README): ``Robot<k>_Odometry.dat`` (time [s], v [m/s], ω [rad/s]),
``Robot<k>_Measurement.dat`` (time [s], barcode, range [m], bearing [rad]), ``Barcodes.dat``
(subject → barcode) and ``Landmark_Groundtruth.dat`` (subject, x, y, σx, σy [m]). ``#`` lines are
headers; columns are separated by tabs and spaces. Subjects 1–5 are robots, 6–20 landmarks.
Measurements quote barcodes, which are mapped to subjects here; observations of robots are dropped.

The data is planar in the dataset's own frame (x, y, counter-clockwise θ; ω > 0 turns left).
The 2D formulas of docs/math.md §6.1 and §7.2 hold in any right-handed planar frame (§1.2), so the
run stays in that frame and never mixes it with robotd's FRD frames.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robotd.core.errors import DatasetError

logger = logging.getLogger(__name__)

LANDMARK_SUBJECTS = range(6, 21)  # subjects 6–20 are landmarks; 1–5 are robots

# In the copy in ../shared/data/mrclam-dataset1-robot1, the measurements labelled subject 11
# (barcode 18) and subject 17 (barcode 61) fit the survey only when exchanged: a dead-reckoned
# map of the first 60 s matches Landmark_Groundtruth.dat with RMSE 2.57 m (similarity scale 0.60)
# as labelled, 0.19 m (scale 1.00) with the two swapped; every pairwise distance involving them is
# off by up to 6 m otherwise. Loaders apply no relabelling by default; pass this to opt in.
MRCLAM1_SWAP_11_17 = {11: 17, 17: 11}


@dataclass(frozen=True, slots=True, eq=False)
class MrclamData:
    """One robot's run. Times are seconds relative to the first odometry sample (``t0_s``)."""

    t0_s: float  # absolute time of the first odometry sample [s, Unix]
    odo_t_s: np.ndarray  # (K,) odometry times
    odo_v_mps: np.ndarray  # (K,) commanded forward velocity, valid from odo_t_s[k] to odo_t_s[k+1]
    odo_w_radps: np.ndarray  # (K,) commanded angular velocity (counter-clockwise positive)
    meas_t_s: np.ndarray  # (N,) landmark observation times (sorted)
    meas_subject: np.ndarray  # (N,) int64 landmark subject number (6–20): the correspondence
    meas_range_m: np.ndarray  # (N,)
    meas_bearing_rad: np.ndarray  # (N,)
    landmark_subject: np.ndarray  # (L,) int64 surveyed landmarks
    landmark_xy_m: np.ndarray  # (L, 2) surveyed positions (Vicon frame)
    landmark_sigma_m: np.ndarray  # (L, 2) survey standard deviations
    n_robot_observations: int  # measurements of other robots, dropped

    def landmark_truth(self) -> dict[int, np.ndarray]:
        """subject -> (2,) surveyed position."""
        return {int(s): self.landmark_xy_m[i] for i, s in enumerate(self.landmark_subject)}

    def until(self, duration_s: float) -> MrclamData:
        """The first ``duration_s`` seconds of the run."""
        ko = self.odo_t_s <= duration_s
        km = self.meas_t_s <= duration_s
        return MrclamData(
            self.t0_s,
            self.odo_t_s[ko],
            self.odo_v_mps[ko],
            self.odo_w_radps[ko],
            self.meas_t_s[km],
            self.meas_subject[km],
            self.meas_range_m[km],
            self.meas_bearing_rad[km],
            self.landmark_subject,
            self.landmark_xy_m,
            self.landmark_sigma_m,
            self.n_robot_observations,
        )


def _table(path: Path, ncols: int) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"MRCLAM: missing file {path}")
    try:
        a = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as exc:
        raise DatasetError(f"MRCLAM: cannot parse {path}: {exc}") from None
    if a.shape[0] == 0 or a.shape[1] != ncols:
        raise DatasetError(f"MRCLAM: {path} expected rows of {ncols} numbers, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise DatasetError(f"MRCLAM: {path} has non-finite values")
    return a


def load_mrclam(data_dir: str | Path, robot: int = 1, relabel: Mapping[int, int] | None = None) -> MrclamData:
    """Load one robot of an MRCLAM dataset folder; raises DatasetError with the path on bad layout.

    ``relabel`` maps measured subject numbers to others (e.g. :data:`MRCLAM1_SWAP_11_17`); the
    surveyed landmarks are never changed.
    """
    d = Path(data_dir)
    if not d.is_dir():
        raise DatasetError(f"MRCLAM: no such folder {d}")
    odo = _table(d / f"Robot{robot}_Odometry.dat", 3)
    meas = _table(d / f"Robot{robot}_Measurement.dat", 4)
    bar = _table(d / "Barcodes.dat", 2).astype(np.int64)
    lm = _table(d / "Landmark_Groundtruth.dat", 5)
    barcode_to_subject = {int(b): int(s) for s, b in bar}
    order = np.argsort(odo[:, 0], kind="stable")
    odo = odo[order]
    t0 = float(odo[0, 0])
    subj = np.array([barcode_to_subject.get(int(b), -1) for b in meas[:, 1]], np.int64)
    if relabel:
        subj = np.array([relabel.get(int(x), int(x)) for x in subj], np.int64)
    unknown = int(np.sum(subj < 0))
    if unknown:
        raise DatasetError(
            f"MRCLAM: {unknown} measurements quote barcodes missing from {d / 'Barcodes.dat'} "
            f"(e.g. {int(meas[np.argmax(subj < 0), 1])})"
        )
    is_lm = np.isin(subj, np.fromiter(LANDMARK_SUBJECTS, np.int64))
    m = meas[is_lm]
    ms = subj[is_lm]
    om = np.argsort(m[:, 0], kind="stable")
    data = MrclamData(
        t0_s=t0,
        odo_t_s=odo[:, 0] - t0,
        odo_v_mps=odo[:, 1].copy(),
        odo_w_radps=odo[:, 2].copy(),
        meas_t_s=m[om, 0] - t0,
        meas_subject=ms[om],
        meas_range_m=m[om, 2].copy(),
        meas_bearing_rad=m[om, 3].copy(),
        landmark_subject=lm[:, 0].astype(np.int64),
        landmark_xy_m=lm[:, 1:3].copy(),
        landmark_sigma_m=lm[:, 3:5].copy(),
        n_robot_observations=int(np.sum(~is_lm)),
    )
    logger.info(
        "MRCLAM %s robot %d: %d odometry rows over %.1f s, %d landmark observations (%d of robots dropped)",
        d,
        robot,
        len(data.odo_t_s),
        float(data.odo_t_s[-1]),
        len(data.meas_t_s),
        data.n_robot_observations,
    )
    return data
