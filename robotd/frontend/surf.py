"""SURF: speeded-up robust features (Bay, Ess, Tuytelaars, Van Gool, CVIU 2008; thesis §4.1.2).

OpenCV's pip wheels leave SURF out (it is in the non-free contrib module), so robotd implements it.
The steps, with the paper's sections:

1. Integral image (thesis eq. 4.1.10), float64 of shape (H+1, W+1).
2. Box-filter approximations Dxx, Dyy, Dxy of the Gaussian second derivatives, normalised by the
   filter area; blob response det = Dxx Dyy - (0.9 Dxy)^2 (eq. 4.1.14, Bay §3.1).
3. Scale space (Bay §3.3): octave o, layer k uses the filter side ``L = 3 (2^(o+1) (k+1) + 1)``, i.e.
   9, 15, 21, 27; 15, 27, 39, 51; 27, 51, 75, 99; ... with the sampling step ``init_sample * 2^o``.
   The image is never resampled, only the filters grow.
4. Non-maximum suppression in the 3x3x3 (x, y, layer) neighbourhood, above ``hessian_threshold``
   (Bay §3.3, after Neubeck & Van Gool).
5. Sub-pixel and sub-scale localisation by the 3D quadratic fit of Brown & Lowe (BMVC 2002): the
   offset -H^-1 g of the sampled det, with one relocation step to the neighbouring sample when an
   offset exceeds 0.75 sample (see ``_octave_keypoints`` for why not 0.5); fits that stay beyond
   one sample, are not maxima (H not negative definite) or fall below the threshold are dropped.
   Bay's octaves overlap in scale, so a blob found in two octaves is kept once (``_distinct``).
6. Orientation from Haar wavelet responses (side 4s, radius 6s, Gaussian sigma 2s) and a sliding
   window of pi/3 (Bay §4.1); the responses are bilinear in the sample position.
7. The descriptor: 20s window along the orientation, 4x4 subregions of 5x5 Haar samples (side 2s,
   Gaussian sigma 3.3s), (sum dx, sum |dx|, sum dy, sum |dy|) per subregion, unit length (Bay §4.2).
   The window is resampled along the keypoint's axes (s x s box means, bilinear) and the wavelets
   are taken on that patch, so they turn with the keypoint (as OpenCV's SURF does).

Measured (tests/robotd/frontend/test_surf.py, KITTI and Middlebury frames): under a 30 deg rotation plus 1.5x zoom
57-64 % of the features repeat and 72-78 % of those match the right feature (nearest neighbour +
ratio 0.8); a 90 deg rotation changes orientations by exactly 90 deg (median error 0.0 deg). For
an isotropic Gaussian blob of std sigma the detected scale is s = 0.70-0.75 sigma at every size:
the nominal s = 1.2 L / 9 of the box filters is below the Gaussian scale they respond like.

Conventions of the returned :class:`~robotd.frontend.features.Features`:

- ``xy`` (N, 2) float32 [px], column/row with pixel centres at integers.
- ``size`` (N,) float32 [px]: the (interpolated) side L of the Hessian box filter that detected the
  feature, OpenCV's ``KeyPoint.size`` convention for SURF, so the scale is ``s = 1.2 * size / 9``
  [px] (the sigma of the Gaussian the filter approximates) and the descriptor window is ``20 s``.
- ``angle`` (N,) float32 [deg] in [0, 360), from +x towards +y (clockwise on screen, OpenCV's
  ``KeyPoint.angle``); -1 when ``upright``.
- ``response`` (N,) float32: the interpolated, area-normalised Hessian determinant.
- ``laplacian`` (N,) int8: sign of Dxx + Dyy, -1 for a bright blob on a dark background, +1 for
  the inverse (never 0: det > 0 implies Dxx and Dyy share a non-zero sign).
- ``desc`` (N, 64) (or 128 when ``extended``) float32, unit length. Features are sorted by
  decreasing response.

The heavy loops (response maps, orientation, descriptor) are numba kernels in ``_surf_kernels``;
their plain numpy/Python twins, ``hessian_layer_reference`` and ``describe_reference`` (the same
mathematics, which the tests compare the kernels against), are in tests/support/reference_surf.py.
Haar samples that fall partly outside the image see zeros there (the box sums are clipped). The
kernels are compiled on first use and cached on disk (:mod:`robotd.core.jit` explains
``NUMBA_CACHE_DIR`` for read-only installs); they release the GIL, so two images can be processed
in two threads.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial import cKDTree

from robotd.core.errors import ConfigError, InputError
from robotd.frontend import _surf_kernels as _k
from robotd.frontend.features import Features

logger = logging.getLogger(__name__)

# Bay et al. §3.1: w = |L_xy(1.2)|_F |D_yy(9)|_F / (|L_yy(1.2)|_F |D_xy(9)|_F) = 0.912, used as 0.9.
HESSIAN_WEIGHT = 0.9
_ORI_BINS = 72  # orientation vote bins of 5 deg
_ORI_WINDOW_BINS = 12  # 12 x 5 deg = pi/3 sliding window
_MAX_OFFSET = 1.0  # largest accepted interpolation offset [samples] after one relocation step
_TWIN_DIST = 0.1  # cross-octave duplicates: distance below this fraction of the filter side ...
_TWIN_SIZE_RATIO = 1.3  # ... and sizes within this ratio
_MAX_CANDIDATES = 1 << 16  # rows of the per-octave maxima buffer (1.5 MB)
_RELOCATE = 0.75  # relocate (Brown & Lowe) only beyond this offset [samples]: see _octave_keypoints


@dataclass(frozen=True, slots=True)
class SurfParams:
    """SURF parameters; defaults follow OpenCV's SURF (threshold 100, 4 octaves) and Bay et al.

    hessian_threshold: minimum area-normalised det of the Hessian, image in 0..255 grey levels
        (the same units as OpenCV's ``hessianThreshold``). Higher: fewer, stronger blobs.
    n_octaves: number of octaves (each doubles the filter size increment and the sampling step).
    n_octave_layers: interior layers per octave in which maxima are searched; each octave
        evaluates ``n_octave_layers + 2`` filter sizes (2 -> 9, 15, 21, 27 as in Bay et al.).
    upright: skip the orientation (U-SURF); ``angle`` is then -1 and descriptors are axis-aligned.
    extended: 128-D descriptor instead of 64-D.
    max_features: keep only the strongest this many (by response); 0 keeps all.
    init_sample: sampling step [px] of the first octave (1 as OpenCV; 2 as Bay et al. and
        OpenSURF, about 3x faster with fewer small-scale features).
    """

    hessian_threshold: float = 100.0
    n_octaves: int = 4
    n_octave_layers: int = 2
    upright: bool = False
    extended: bool = False
    max_features: int = 1000
    init_sample: int = 1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.hessian_threshold) and self.hessian_threshold > 0):
            raise ConfigError(f"surf.hessian_threshold: expected a finite value > 0, got {self.hessian_threshold}")
        for name, lo in (("n_octaves", 1), ("n_octave_layers", 1), ("max_features", 0), ("init_sample", 1)):
            v = getattr(self, name)
            if not isinstance(v, int | np.integer) or isinstance(v, bool) or v < lo:
                raise ConfigError(f"surf.{name}: expected an integer >= {lo}, got {v!r}")
        if self.n_octaves > 10:
            raise ConfigError(f"surf.n_octaves: expected at most 10, got {self.n_octaves}")


def filter_size(octave: int, layer: int) -> int:
    """Side L [px] of the box filters of ``layer`` in ``octave`` (Bay et al. §3.3): 3 (2^(o+1) (k+1) + 1)."""
    return 3 * ((2 ** (octave + 1)) * (layer + 1) + 1)


def integral_image(image: np.ndarray) -> np.ndarray:
    """Integral image (thesis eq. 4.1.10) of a (H, W) image: (H+1, W+1) float64, ii[r, c] = sum image[:r, :c]."""
    return cv2.integral(image, sdepth=cv2.CV_64F)


def _validate(image: object, mask: object) -> tuple[np.ndarray, np.ndarray | None]:
    if not isinstance(image, np.ndarray):
        raise InputError(f"surf: expected a numpy array image, got {type(image).__name__}")
    if image.ndim != 2:
        raise InputError(f"surf: expected a (H, W) grey image, got shape {image.shape}")
    if image.dtype != np.uint8:
        raise InputError(f"surf: expected dtype uint8, got {image.dtype} (shape {image.shape})")
    if mask is None:
        return image, None
    if not isinstance(mask, np.ndarray) or mask.shape != image.shape:
        got = mask.shape if isinstance(mask, np.ndarray) else type(mask).__name__
        raise InputError(f"surf: expected a mask of shape {image.shape}, got {got}")
    return image, mask


@dataclass(frozen=True, slots=True)
class SurfKeypoints:
    """Detected keypoints before description (the output of :func:`detect`), strongest first."""

    xy: np.ndarray  # (N, 2) float64 [px]
    size: np.ndarray  # (N,) float64 [px] filter side L
    response: np.ndarray  # (N,) float64
    laplacian: np.ndarray  # (N,) int8


def candidate_ranges(
    sizes: np.ndarray, step: int, shape: tuple[int, int], ny: int, nx: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inclusive grid-index ranges (lo, hi_i, hi_j), each (n_layers,), searched for maxima per layer.

    Layer k needs layer k+1 (its largest neighbour filter) to fit inside the image at the 3x3
    neighbours of the centre, so the range is that of layer k+1 shrunk by one sample.
    """
    h, w = shape
    n_layers = len(sizes)
    lo = np.empty(n_layers, np.int64)
    hi_i = np.empty(n_layers, np.int64)
    hi_j = np.empty(n_layers, np.int64)
    for k in range(n_layers):
        half = int(sizes[min(k + 1, n_layers - 1)]) // 2
        lo[k] = -(-half // step) + 1
        hi_i[k] = min((h - 1 - half) // step, ny - 1) - 1
        hi_j[k] = min((w - 1 - half) // step, nx - 1) - 1
    return lo, hi_i, hi_j


def local_maxima_numpy(
    det: np.ndarray, lo: np.ndarray, hi_i: np.ndarray, hi_j: np.ndarray, threshold: float
) -> np.ndarray:
    """(M, 3) int64 rows (layer, i, j) of the 3x3x3 maxima of ``det`` (n_layers, ny, nx): numpy
    version of the kernel's scan (Bay §3.3, same tie rule), in (layer, i, j) order.

    The runtime fallback of :func:`detect` when the maxima outnumber the kernel's candidate buffer
    (``_MAX_CANDIDATES``); the tests also hold the kernel's scan to it (identical rows).
    """
    n_layers, ny, nx = det.shape
    flat = det.reshape(-1)
    parts = []
    for k in range(1, n_layers - 1):
        a, bi, bj = int(lo[k]), int(hi_i[k]), int(hi_j[k])
        if bi < a or bj < a:
            continue
        ii, jj = np.nonzero(det[k, a : bi + 1, a : bj + 1] > threshold)
        parts.append((k * ny + ii + a) * nx + jj + a)
    idx = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    v = flat[idx]
    keep = np.ones(idx.shape, bool)
    for dl in (-1, 0, 1):
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                off = (dl * ny + di) * nx + dj
                if off == 0:
                    continue
                # Ties: beat the neighbours before in raster order, at least equal those after.
                keep &= (v > flat[idx + off]) if off < 0 else (v >= flat[idx + off])
    layer, rem = np.divmod(idx[keep], ny * nx)
    i, j = np.divmod(rem, nx)
    return np.stack([layer, i, j], axis=1).astype(np.int64)


def _octave_keypoints(
    det: np.ndarray,
    trace: np.ndarray,
    sizes: np.ndarray,
    step: int,
    cand: np.ndarray,
    lo: np.ndarray,
    hi_i: np.ndarray,
    hi_j: np.ndarray,
    threshold: float,
) -> SurfKeypoints | None:
    """Refine one octave's maxima ``cand`` (M, 3) rows (layer, i, j) to sub-pixel/sub-scale keypoints."""
    n_layers = det.shape[0]
    if len(cand) == 0:
        return None
    layer, i, j = cand[:, 0].copy(), cand[:, 1].copy(), cand[:, 2].copy()

    offset, value, ok = _quadratic_fit(det, layer, i, j)
    # Brown & Lowe: an offset beyond half a sample means the extremum is nearer the neighbour: move
    # there once and refit, if the neighbour is still a valid interior sample. The move starts at
    # 0.75 rather than 0.5: the det is skewed along scale, so a peak midway between two layers
    # gives offsets just above 0.5 from both sides, and the refit from the far side leaked up to
    # 0.8 px of error into x, y through the cross terms (Gaussian blobs, step 4); with 0.75 the
    # worst blob error fell from 0.79 px to 0.19 px and real-image repeatability did not drop.
    move = ok & (np.abs(offset) > _RELOCATE).any(axis=1)
    if move.any():
        step_ = np.clip(np.round(offset[move]), -1, 1).astype(np.int64)  # (M, 3) in (x, y, layer)
        nj, ni, nl = j[move] + step_[:, 0], i[move] + step_[:, 1], layer[move] + step_[:, 2]
        inside = (nl >= 1) & (nl <= n_layers - 2)
        nl_c = np.clip(nl, 1, n_layers - 2)
        inside &= (ni >= lo[nl_c]) & (ni <= hi_i[nl_c]) & (nj >= lo[nl_c]) & (nj <= hi_j[nl_c])
        idx = np.flatnonzero(move)
        ok[idx[~inside]] = False
        idx = idx[inside]
        layer[idx], i[idx], j[idx] = nl[inside], ni[inside], nj[inside]
        off2, val2, ok2 = _quadratic_fit(det, layer[idx], i[idx], j[idx])
        offset[idx], value[idx], ok[idx] = off2, val2, ok2
    # After the relocation, accept offsets up to one sample (OpenCV's bound): on real images this keeps
    # about 5 % more features and raised the repeatability under rotation + scale by 2-6 points
    # (KITTI, Middlebury) compared with Brown & Lowe's strict half sample.
    ok &= (np.abs(offset) <= _MAX_OFFSET).all(axis=1) & (value > threshold)
    layer, i, j, offset, value = layer[ok], i[ok], j[ok], offset[ok], value[ok]
    if layer.size == 0:
        return None
    # Two maxima may converge onto one sample after relocation: keep one.
    _, first = np.unique(np.stack([layer, i, j], axis=1), axis=0, return_index=True)
    layer, i, j, offset, value = layer[first], i[first], j[first], offset[first], value[first]

    d_size = float(sizes[1] - sizes[0])  # uniform within an octave
    xy = np.stack([(j + offset[:, 0]) * step, (i + offset[:, 1]) * step], axis=1).astype(np.float64)
    size = sizes[layer].astype(np.float64) + offset[:, 2] * d_size
    lap = np.where(trace[layer, i, j] < 0, -1, 1).astype(np.int8)
    return SurfKeypoints(xy, size, value, lap)


def _quadratic_fit(
    det: np.ndarray, layer: np.ndarray, i: np.ndarray, j: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Brown & Lowe (2002) 3D quadratic fit around samples (layer, i, j) of ``det``.

    With g and H the central-difference gradient and Hessian of det in (x=j, y=i, s=layer) sample
    units, the extremum is at offset = -H^-1 g and its value det + g.offset / 2. Returns the (N, 3)
    offsets (x, y, s), the (N,) values and the (N,) mask of well-conditioned fits.

    Known limit: the det's x-curvature changes with scale (a cubic term the quadratic lacks), so
    when a blob lies midway between two samples *and* two layers the cross terms move x, y by up
    to 0.3 sample (1.2 px at step 4 for a synthetic blob; typically < 0.06 px). Fitting x, y
    in-layer and s separately removes that on blobs but matched real images worse (KITTI 30 deg
    + 1.5x: 0.67-0.74 correct instead of 0.78), so the full 3D fit stays.
    """

    def d(dl: int, di: int, dj: int) -> np.ndarray:
        return det[layer + dl, i + di, j + dj].astype(np.float64)

    c = d(0, 0, 0)
    gx = (d(0, 0, 1) - d(0, 0, -1)) / 2
    gy = (d(0, 1, 0) - d(0, -1, 0)) / 2
    gs = (d(1, 0, 0) - d(-1, 0, 0)) / 2
    hxx = d(0, 0, 1) + d(0, 0, -1) - 2 * c
    hyy = d(0, 1, 0) + d(0, -1, 0) - 2 * c
    hss = d(1, 0, 0) + d(-1, 0, 0) - 2 * c
    hxy = (d(0, 1, 1) - d(0, 1, -1) - d(0, -1, 1) + d(0, -1, -1)) / 4
    hxs = (d(1, 0, 1) - d(1, 0, -1) - d(-1, 0, 1) + d(-1, 0, -1)) / 4
    hys = (d(1, 1, 0) - d(1, -1, 0) - d(-1, 1, 0) + d(-1, -1, 0)) / 4
    hess = np.stack(
        [np.stack([hxx, hxy, hxs], -1), np.stack([hxy, hyy, hys], -1), np.stack([hxs, hys, hss], -1)], axis=1
    )
    g = np.stack([gx, gy, gs], axis=1)
    # A maximum has a negative definite Hessian; a singular or indefinite fit is rejected rather
    # than extrapolated. Cheap Sylvester test on -H.
    m1 = -hxx
    m2 = hxx * hyy - hxy * hxy
    m3 = np.linalg.det(hess) if len(c) else np.zeros(0)
    scale_ = np.maximum(np.abs(c), 1e-12)
    ok = (m1 > 0) & (m2 > 0) & (-m3 > 1e-12 * scale_**3)
    safe = np.where(ok[:, None, None], hess, -np.eye(3))
    offset = -np.linalg.solve(safe, g[..., None])[..., 0]
    value = c + 0.5 * np.einsum("ni,ni->n", g, offset)
    return offset, value, ok


def detect(image: np.ndarray, params: SurfParams | None = None, ii: np.ndarray | None = None) -> SurfKeypoints:
    """Detect SURF keypoints (steps 1-5) of a (H, W) uint8 image, sorted by response, undescribed.

    ii: the image's integral image (H+1, W+1) float64 when the caller already has it.
    """
    p = params or SurfParams()
    image, _ = _validate(image, None)
    h, w = image.shape
    if image.size == 0:
        return SurfKeypoints(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, np.int8))
    if ii is None:
        ii = integral_image(np.ascontiguousarray(image))
    elif ii.shape != (h + 1, w + 1) or ii.dtype != np.float64:
        raise InputError(f"surf: expected a float64 integral image {(h + 1, w + 1)}, got {ii.dtype} {ii.shape}")
    n_layers = p.n_octave_layers + 2
    found: list[SurfKeypoints] = []
    for o in range(p.n_octaves):
        step = p.init_sample * (2**o)
        sizes = np.array([filter_size(o, k) for k in range(n_layers)], np.int64)
        # Stop when even the largest filter of the octave plus a 3x3 neighbourhood no longer fits.
        if sizes[-1] + 2 * step > min(h, w):
            break
        ny = (h - 1) // step + 1
        nx = (w - 1) // step + 1
        det = np.empty((n_layers, ny, nx), np.float32)
        trace = np.empty((n_layers, ny, nx), np.float32)
        lo, hi_i, hi_j = candidate_ranges(sizes, step, (h, w), ny, nx)
        # Maxima of one layer are never 8-adjacent, which bounds their number; the buffer is capped
        # (a 4000 x 3000 image would need 140 MB) and the rare overflow rescans in numpy.
        capacity = min((n_layers - 2) * ((ny + 1) // 2) * ((nx + 1) // 2), _MAX_CANDIDATES)
        cand = np.empty((capacity, 3), np.int64)
        n_cand = _k.hessian_layers(
            ii, sizes, step, ny, nx, HESSIAN_WEIGHT, det, trace, p.hessian_threshold, lo, hi_i, hi_j, cand
        )
        if n_cand > capacity:
            logger.debug("surf: %d maxima in octave %d exceed the buffer of %d; numpy rescan", n_cand, o, capacity)
            cand = local_maxima_numpy(det, lo, hi_i, hi_j, p.hessian_threshold)
        else:
            cand = cand[:n_cand]
        kp = _octave_keypoints(det, trace, sizes, step, cand, lo, hi_i, hi_j, p.hessian_threshold)
        if kp is not None:
            found.append(kp)
    if not found:
        return SurfKeypoints(np.zeros((0, 2)), np.zeros(0), np.zeros(0), np.zeros(0, np.int8))
    xy = np.concatenate([k.xy for k in found])
    size = np.concatenate([k.size for k in found])
    response = np.concatenate([k.response for k in found])
    lap = np.concatenate([k.laplacian for k in found])
    order = np.argsort(-response, kind="stable")
    xy, size, response, lap = xy[order], size[order], response[order], lap[order]
    keep = _distinct(xy, size, lap)
    return SurfKeypoints(xy[keep], size[keep], response[keep], lap[keep])


def _distinct(xy: np.ndarray, size: np.ndarray, lap: np.ndarray) -> np.ndarray:
    """Mask of the keypoints (sorted strongest first) that are not a weaker copy of another.

    Bay's octaves overlap in scale (the layers 27 and 39 of octave 1 and 51 of octave 2 bracket the
    same range), so one blob is often found in two octaves, a few percent of the size apart. Such
    twins have near-identical descriptors, which makes Lowe's ratio test reject the true match
    (about 7 % of KITTI features were twins). A keypoint is dropped when a stronger one with the same
    Laplacian sign lies within 0.1 of the smaller filter side and the sizes differ by < 30 %.
    """
    n = len(xy)
    keep = np.ones(n, bool)
    if n < 2:
        return keep
    pairs = cKDTree(xy).query_pairs(r=_TWIN_DIST * float(size.max()), output_type="ndarray")
    if len(pairs) == 0:
        return keep
    a, b = pairs.min(axis=1), pairs.max(axis=1)  # a is the stronger (sorted by response)
    small = np.minimum(size[a], size[b])
    twin = (
        (np.linalg.norm(xy[a] - xy[b], axis=1) < _TWIN_DIST * small)
        & (np.maximum(size[a], size[b]) < _TWIN_SIZE_RATIO * small)
        & (lap[a] == lap[b])
    )
    keep[b[twin]] = False
    return keep


def detect_and_compute(
    image: np.ndarray,
    params: SurfParams | None = None,
    mask: np.ndarray | None = None,
    select: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> Features:
    """SURF keypoints and descriptors of a grey image.

    image: (H, W) uint8. params: :class:`SurfParams` (defaults when None). mask: optional (H, W)
    array; only features whose rounded position has a non-zero mask value are kept.
    select: optional ``select(xy (N, 2) float64 [px], response (N,)) -> indices or boolean mask``
    applied to the detected keypoints (strongest first, after the mask) *before* the descriptors
    are computed, e.g. a caller's spatial bucketing: describing costs 10-15 us per feature, so
    selecting first avoids describing features that would be thrown away.
    Returns :class:`Features` (see the module docstring for every field's convention), in the
    order kept (strongest first unless ``select`` reorders), at most ``params.max_features`` of
    them. Empty, tiny or featureless images give zero features; a wrong type, shape or dtype raises
    :class:`~robotd.core.errors.InputError`.
    """
    p = params or SurfParams()
    image, mask = _validate(image, mask)
    dim = 128 if p.extended else 64
    if image.size == 0:
        return Features.empty(dim)
    image = np.ascontiguousarray(image)
    ii = integral_image(image)
    kp = detect(image, p, ii)
    xy, size, response, lap = kp.xy, kp.size, kp.response, kp.laplacian
    if mask is not None and len(xy):
        c = np.clip(np.rint(xy[:, 0]).astype(np.int64), 0, image.shape[1] - 1)
        r = np.clip(np.rint(xy[:, 1]).astype(np.int64), 0, image.shape[0] - 1)
        inside = mask[r, c] != 0
        xy, size, response, lap = xy[inside], size[inside], response[inside], lap[inside]
    if select is not None and len(xy):
        keep = np.asarray(select(xy, response))
        if keep.dtype != bool and not np.issubdtype(keep.dtype, np.integer):
            raise InputError(f"surf: select must return indices or a boolean mask, got dtype {keep.dtype}")
        if keep.dtype == bool and keep.shape != (len(xy),):
            raise InputError(f"surf: select returned a mask of shape {keep.shape}, expected ({len(xy)},)")
        xy, size, response, lap = xy[keep], size[keep], response[keep], lap[keep]
    if p.max_features and len(xy) > p.max_features:
        # Strongest first (or the caller's order from select).
        cap = slice(0, p.max_features)
        xy, size, response, lap = xy[cap], size[cap], response[cap], lap[cap]
    n = len(xy)
    if n == 0:
        return Features.empty(dim)
    scale = size * (1.2 / 9.0)
    angle = np.empty(n, np.float64)
    desc = np.empty((n, dim), np.float32)
    _k.orient_and_describe(
        ii, np.ascontiguousarray(xy), scale, p.upright, p.extended, _ORI_BINS, _ORI_WINDOW_BINS, angle, desc
    )
    if p.upright:
        angle_deg = np.full(n, -1.0, np.float32)
    else:
        angle_deg = np.mod(np.degrees(angle), 360.0).astype(np.float32)
        angle_deg[angle_deg >= 360.0] = 0.0  # float32 rounding of 359.99999...
    logger.debug("surf: %d features on %dx%d", n, image.shape[1], image.shape[0])
    return Features(
        xy.astype(np.float32),
        size.astype(np.float32),
        angle_deg,
        response.astype(np.float32),
        lap.astype(np.int8),
        desc,
        False,
    )
