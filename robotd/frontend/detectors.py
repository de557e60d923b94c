"""Feature detectors behind one interface: ORB (fast default), SIFT (OpenCV), SURF (robotd's own).

``make_detector(params).detect(image, max_features) -> Features`` (docs/math.md §4.1). A per-frame
cap keeps the cost bounded; grid bucketing spreads the kept features over the image, which matters
for the outlier stage and the filters: a cluster of features on one parked car constrains the pose
far less than the same number spread over the view.

Descriptor conventions are those of :class:`robotd.frontend.features.Features`: SIFT (128-D) and
SURF (64-D) float32 with Euclidean distance, ORB 32-byte packed bits with Hamming distance.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from typing import Any, Protocol

import cv2
import numpy as np

from robotd.core.choices import DETECTORS
from robotd.core.errors import ConfigError, InputError
from robotd.frontend import _detect_kernels as _dk
from robotd.frontend.features import Features

logger = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class DetectorParams:
    """Detector configuration (config key ``frontend.detector``).

    name: "orb" (default: ≈4 ms per KITTI frame), "sift" (OpenCV SIFT, ≈50 ms) or "surf" (robotd's).
    max_features: per-frame cap after bucketing.
    bucketing: keep the strongest features per cell of a grid_rows × grid_cols grid, so that the
      kept features cover the image (cell quota = ceil(max_features / cells); unused quota of
      sparse cells is refilled with the strongest remaining features).
    oversample: how many candidates (× max_features) the detector may return before bucketing.
    orb_*: cv2.ORB knobs (FAST threshold, pyramid scale factor and levels, patch size, and the score
      that ranks candidates: "fast" (default) or "harris" (Harris corner measure on the FAST corners).
      FAST scoring is ≈ 1 ms per 640×400 image cheaper and, with grid bucketing, measured better on
      kitti-seq1: replay drift 0.98 % → 0.84 %, ATE 0.149 → 0.105 m; frame-to-frame median relative
      translation error 0.037 → 0.021 at 640×400 (bench/frontend.py).
      Pyramid: 5 levels at scale 1.44 (span 1.44⁴ ≈ 4.3, more than OpenCV's default 8 × 1.2, 1.2⁷ ≈
      3.6) runs FAST on ≈ 40 % fewer pixels (detect 5.2 → 3.4 ms CPU per 640×400 image) and puts
      more of the quota on the fine levels: kitti-seq1 drift 0.84 → 0.56 %, ATE 0.105 → 0.052 m,
      640×400 frame-to-frame median error 0.021 → 0.018; the simulated rover's 300 frames ATE 22 → 9 mm.
    sift_*: cv2.SIFT knobs (contrast and edge thresholds, layers per octave).
    surf_hessian_threshold: passed to the SURF module when its params accept it (None: its default,
      OpenCV's 100). 20: low enough that the feature cap binds on every KITTI image, so the cap and
      the bucketing choose the strongest *spread* features as they do for ORB and SIFT (at 100
      only 680-900 of 1000 come out on KITTI; docs/frontend.md "SURF").
    """

    name: str = "orb"
    max_features: int = 1000
    bucketing: bool = True
    grid_rows: int = 4
    grid_cols: int = 8
    oversample: float = 4.0
    orb_fast_threshold: int = 12
    orb_scale_factor: float = 1.44
    orb_n_levels: int = 5
    orb_patch_size: int = 31
    orb_score: str = "fast"
    sift_contrast_threshold: float = 0.02
    sift_edge_threshold: float = 10.0
    sift_n_octave_layers: int = 3
    surf_hessian_threshold: float | None = 20.0

    def __post_init__(self) -> None:
        if self.name not in DETECTORS:
            raise ConfigError(f"frontend.detector.name: expected one of {DETECTORS}, got {self.name!r}")
        if self.max_features < 1:
            raise ConfigError(f"frontend.detector.max_features: expected >= 1, got {self.max_features}")
        if self.grid_rows < 1 or self.grid_cols < 1:
            raise ConfigError(
                f"frontend.detector.grid_rows/grid_cols: expected >= 1, got {self.grid_rows}×{self.grid_cols}"
            )
        if self.orb_score not in ("harris", "fast"):
            raise ConfigError(f"frontend.detector.orb_score: expected 'harris' or 'fast', got {self.orb_score!r}")
        if self.oversample < 1.0:
            raise ConfigError(f"frontend.detector.oversample: expected >= 1, got {self.oversample}")


class Detector(Protocol):
    """Detect and describe features of one grey image."""

    name: str
    binary: bool  # True: packed-bit descriptors (Hamming); False: float32 (Euclidean)

    def detect(self, image: np.ndarray, max_features: int | None = None) -> Features:
        """(H, W) uint8 image -> at most ``max_features`` (default: params.max_features) features."""
        ...


def check_image(image: Any, name: str = "image") -> np.ndarray:
    """Validate a grey image at the border: (H, W) uint8 (an (H, W, 3) BGR image is converted)."""
    if not isinstance(image, np.ndarray):
        raise InputError(f"{name}: expected numpy array (H, W) uint8, got {type(image).__name__}")
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise InputError(f"{name}: expected a 2-D grey image (H, W), got shape {image.shape}")
    if image.dtype != np.uint8:
        raise InputError(f"{name}: expected dtype uint8, got {image.dtype}")
    return image


def keypoints_to_arrays(kps: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """cv2.KeyPoint sequence -> xy (N, 2), size (N,), angle (N,), response (N,), all float32."""
    n = len(kps)
    if n == 0:
        z = np.zeros(0, np.float32)
        return np.zeros((0, 2), np.float32), z, z.copy(), z.copy()
    xy = np.asarray(cv2.KeyPoint.convert(kps), dtype=np.float32).reshape(n, 2)
    size = np.fromiter((k.size for k in kps), np.float32, n)
    angle = np.fromiter((k.angle for k in kps), np.float32, n)
    response = np.fromiter((k.response for k in kps), np.float32, n)
    return xy, size, angle, response


def bucket_select(
    xy: np.ndarray, response: np.ndarray, shape: tuple[int, int], max_features: int, grid_rows: int, grid_cols: int
) -> np.ndarray:
    """Indices of at most ``max_features`` features, spread over a grid (strongest per cell first).

    ``xy``: (N, 2) [px] (column, row); ``response``: (N,); ``shape``: (H, W). Each cell keeps up to
    ceil(max_features / cells) of its strongest features; the quota unused by sparse cells is
    filled with the strongest of the remaining features. Returned in decreasing response order.
    (numba kernel; its numpy twin ``bucket_select_numpy`` is in tests/support/reference_frontend.py.)
    """
    n = xy.shape[0]
    if n <= max_features:
        return np.argsort(-response, kind="stable")
    h, w = shape
    col = np.clip((xy[:, 0] * grid_cols / max(w, 1)).astype(np.int64), 0, grid_cols - 1)
    row = np.clip((xy[:, 1] * grid_rows / max(h, 1)).astype(np.int64), 0, grid_rows - 1)
    resp: np.ndarray = np.ascontiguousarray(response, dtype=np.float32 if response.dtype == np.float32 else np.float64)
    cell = row * grid_cols + col
    n_cells = grid_rows * grid_cols
    # (−response, cell, index) order from two stable sorts; a small cell key sorts by radix
    by_cell = np.argsort(cell.astype(np.int16) if n_cells <= np.iinfo(np.int16).max else cell, kind="stable")
    g = by_cell[np.argsort(np.negative(resp[by_cell]), kind="stable")]
    out: np.ndarray = _dk.bucket_kernel(g, cell, resp, int(max_features), n_cells)
    return out


def warmup() -> None:
    """Compile or load the bucketing kernel now (the daemon calls it at start-up)."""
    idx = np.arange(3, dtype=np.int64)
    _dk.bucket_kernel(idx, np.array([0, 1, 1], np.int64), np.array([3.0, 2.0, 1.0], np.float32), 2, 2)


class _OpenCVDetector:
    """ORB or SIFT through OpenCV: detect candidates, bucket, then describe only the kept ones."""

    def __init__(self, params: DetectorParams) -> None:
        self.params = params
        self.name = params.name
        self.binary = params.name == "orb"
        n_cand = int(np.ceil(params.max_features * (params.oversample if params.bucketing else 1.0)))
        self._n_cand = n_cand
        self._impl: Any
        if params.name == "orb":
            self._impl = cv2.ORB.create(
                nfeatures=n_cand,
                scaleFactor=params.orb_scale_factor,
                nlevels=params.orb_n_levels,
                edgeThreshold=params.orb_patch_size,
                patchSize=params.orb_patch_size,
                fastThreshold=params.orb_fast_threshold,
                scoreType=cv2.ORB_HARRIS_SCORE if params.orb_score == "harris" else cv2.ORB_FAST_SCORE,
            )
        else:
            self._impl = cv2.SIFT.create(
                nfeatures=n_cand,
                nOctaveLayers=params.sift_n_octave_layers,
                contrastThreshold=params.sift_contrast_threshold,
                edgeThreshold=params.sift_edge_threshold,
            )

    def detect(self, image: np.ndarray, max_features: int | None = None) -> Features:
        image = check_image(image)
        cap = self.params.max_features if max_features is None else int(max_features)
        dim = 32 if self.binary else 128
        if image.size == 0 or cap <= 0:
            return Features.empty(dim, self.binary)
        kps = self._impl.detect(image, None)
        if not kps:
            return Features.empty(dim, self.binary)
        # candidates: only positions and responses are needed to choose (size and angle are not)
        xy = np.asarray(cv2.KeyPoint.convert(kps), dtype=np.float32).reshape(len(kps), 2)
        resp = np.fromiter((k.response for k in kps), np.float32, len(kps))
        if self.params.bucketing:
            keep = bucket_select(xy, resp, image.shape[:2], cap, self.params.grid_rows, self.params.grid_cols)
        else:
            keep = np.argsort(-resp, kind="stable")[:cap]
        kps = [kps[i] for i in keep]
        kps, desc = self._impl.compute(image, kps)
        if desc is None or not kps:
            return Features.empty(dim, self.binary)
        xy, size, angle, resp = keypoints_to_arrays(kps)
        desc = np.ascontiguousarray(desc, dtype=np.uint8 if self.binary else np.float32)
        lap = np.zeros(len(kps), np.int8)
        return Features(xy, size, angle, resp, lap, desc, self.binary)


class _SurfDetector:
    """robotd's own SURF (robotd.frontend.surf); bucketing and the cap are applied here."""

    def __init__(self, params: DetectorParams) -> None:
        try:
            from robotd.frontend import surf
        except ImportError as exc:  # the SURF module is developed separately
            raise ConfigError(
                f"frontend.detector.name = 'surf': robotd.frontend.surf is not available ({exc}); use 'orb' or 'sift'"
            ) from exc
        self._surf: Any = surf
        self.params = params
        self.name = "surf"
        self.binary = False
        self._surf_params: Any = None
        p_cls = getattr(surf, "SurfParams", None)
        kwargs: dict[str, Any] = {}
        if params.surf_hessian_threshold is not None:
            kwargs["hessian_threshold"] = params.surf_hessian_threshold
        names = {f.name for f in dataclasses.fields(p_cls)} if dataclasses.is_dataclass(p_cls) else set()
        if "max_features" in names:
            # let SURF return the oversampled candidate set; the cap and bucketing are applied here
            kwargs["max_features"] = int(np.ceil(params.max_features * (params.oversample if params.bucketing else 1)))
        if kwargs:
            if p_cls is None:
                raise ConfigError("frontend.detector.surf_*: robotd.frontend.surf has no SurfParams")
            try:
                self._surf_params = p_cls(**kwargs)
            except TypeError as exc:
                raise ConfigError(f"frontend.detector.surf_*: SurfParams rejected {kwargs} ({exc})") from exc

    def detect(self, image: np.ndarray, max_features: int | None = None) -> Features:
        image = check_image(image)
        cap = self.params.max_features if max_features is None else int(max_features)
        if image.size == 0 or cap <= 0:
            return Features.empty(64, False)
        f: Features = self._surf.detect_and_compute(image, self._surf_params)
        if f.n == 0:
            return f
        if self.params.bucketing:
            keep = bucket_select(f.xy, f.response, image.shape[:2], cap, self.params.grid_rows, self.params.grid_cols)
        else:
            keep = np.argsort(-f.response, kind="stable")[:cap]
        return f.subset(keep)


def make_detector(params: DetectorParams | None = None) -> Detector:
    """The detector named by ``params.name`` (default ORB). SURF raises ConfigError if unavailable."""
    params = params or DetectorParams()
    if params.name == "surf":
        return _SurfDetector(params)
    return _OpenCVDetector(params)


def surf_available() -> bool:
    """True when robotd.frontend.surf can be imported (it is developed separately)."""
    try:
        from robotd.frontend import surf  # noqa: F401
    except ImportError:
        return False
    return True
