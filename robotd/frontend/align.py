"""The current frame's pixels of a frame-to-frame match, moved onto the previous frame's patch.

The stereo PnP (robotd.frontend.pnp) measures the motion between two frames from descriptor
matches: the previous frame's point, triangulated from its keypoint, against the current frame's
keypoint. Both keypoints are where the detector put them, and ORB's FAST corners stick to the
pixel grid: an image shifted by a quarter of a pixel moves most of them not at all (measured
0.14 px for 0.25 px, 0.40 px for 0.5 px, on a real KITTI image and on renders alike). When the
image moves by a pixel or less between frames (a rover's few centimetres a frame; any far point)
the two keypoints of a match are then not the same point of the scene, and the motion they imply
is short: a rover's 3.7 cm steps in open terrain came out at 0.82 of the truth
(docs/frontend.md "Short steps in open terrain").

:func:`align_to_previous` measures where the previous keypoint's patch is in the current image:
the shift s of the current keypoint minimising the zero-mean squared difference

    Σ_u [ (I_c(x_c + s + u) − Ī_c) − (I_p(x_p + u) − Ī_p) ]²

over a (2h+1)² patch (h = ``ALIGN_HALF_PX``, 9 × 9), by inverse-compositional Gauss–Newton
(Lucas–Kanade with the template's gradients, so the 2 × 2 normal matrix is built once per point)
on bilinear samples. The zero means make it insensitive to a change of brightness between frames.
A shift is kept when it converges (the last step under 0.01 px) within ``max_px`` of the keypoint,
when the template has a corner (its normal matrix's smaller eigenvalue is not negligible), and when
the patch's scale barely changes between the frames: a translation is the patch's whole motion only
while the point's depth does, so a match whose disparity changes by more than
``MAX_SCALE_CHANGE`` (5 %, a 9 × 9 patch's edge moving 0.2 px) keeps its keypoint. The right
column moves with the left one (the disparity at the keypoint stays: the patch's neighbour is at
its depth), and the caller re-triangulates the current point from the aligned pixels.

Numba kernel: robotd.frontend._align_kernels; numpy twin in tests/support/reference_frontend.py.
"""

from __future__ import annotations

import numpy as np

from robotd.core.errors import InputError
from robotd.frontend import _align_kernels as _k

ALIGN_HALF_PX = 4  # 9 × 9 patches
ALIGN_ITERATIONS = 10  # Gauss–Newton passes at most (3–4 usually converge)
MAX_SCALE_CHANGE = 0.05  # |d_curr / d_prev − 1| beyond which a match keeps its keypoint


def align_to_previous(
    prev_img: np.ndarray,
    curr_img: np.ndarray,
    z_prev: np.ndarray,
    z: np.ndarray,
    max_px: float,
    half: int = ALIGN_HALF_PX,
) -> tuple[np.ndarray, np.ndarray]:
    """Aligned current pixels (N, 3) = (x_l, x_r, y) and which were moved (N,) bool.

    ``prev_img``, ``curr_img``: (H, W) uint8 left images of the previous and the current frame;
    ``z_prev``, ``z``: (N, 3) [px] the matches' (x_l, x_r, y) in each. Rows not moved are ``z``'s.
    """
    z_prev = np.asarray(z_prev, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2 or z.shape[1] != 3 or z_prev.shape != z.shape:
        raise InputError(f"align_to_previous: expected z and z_prev of one shape (N, 3), got {z.shape}, {z_prev.shape}")
    if np.ndim(prev_img) != 2 or np.shape(prev_img) != np.shape(curr_img):
        raise InputError(
            f"align_to_previous: expected two images of one size (H, W), got {np.shape(prev_img)}, {np.shape(curr_img)}"
        )
    if not (max_px > 0 and half >= 1):
        raise InputError(f"align_to_previous: expected max_px > 0 and half >= 1, got {max_px}, {half}")
    n = z.shape[0]
    dx, dy, ok = np.zeros(n), np.zeros(n), np.zeros(n, bool)
    if n == 0:
        return z.copy(), ok
    finite = np.isfinite(z).all(axis=1) & np.isfinite(z_prev).all(axis=1)
    xp, yp = np.where(finite, z_prev[:, 0], -1e9), np.where(finite, z_prev[:, 2], -1e9)  # off the image: skipped
    _k.align_kernel(
        np.ascontiguousarray(prev_img, dtype=np.uint8),
        np.ascontiguousarray(curr_img, dtype=np.uint8),
        xp,
        yp,
        np.where(finite, z[:, 0], -1e9),
        np.where(finite, z[:, 2], -1e9),
        int(half),
        ALIGN_ITERATIONS,
        float(max_px),
        dx,
        dy,
        ok,
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (z[:, 0] - z[:, 1]) / (z_prev[:, 0] - z_prev[:, 1])
    ok &= np.abs(ratio - 1.0) <= MAX_SCALE_CHANGE
    out = z.copy()
    out[ok, 0] += dx[ok]
    out[ok, 1] += dx[ok]
    out[ok, 2] += dy[ok]
    return out, ok


def warmup() -> None:
    """Compile or load the kernel now (tiny inputs, the daemon's dtypes)."""
    img = np.zeros((32, 32), np.uint8)
    img[10:20, 12:22] = 200
    z = np.array([[16.0, 12.0, 15.0]])
    align_to_previous(img, img, z, z, 1.5)
