"""Stereo matching (docs/math.md §4.1–§4.2): distances, ratio and cross check, candidates, refinement."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from robotd.core.errors import ConfigError, InputError
from robotd.core.stereo import RectifiedStereo, gate_selection_shift
from robotd.frontend.detectors import DetectorParams, make_detector
from robotd.frontend.features import Features
from robotd.frontend.stereo_match import (
    StereoMatchParams,
    candidate_pairs,
    distance_matrix,
    match_stereo,
    normalise_descriptors,
    pair_distances,
    ratio_and_cross_check,
    refine_disparity,
)
from tests.support.images import smooth_texture
from tests.support.tolerances import FLOAT32_ARITH_TOL


def _middlebury(shared_data):
    d = shared_data("stereo-calib", "middlebury-cones")
    left = cv2.imread(str(d / "left.png"), cv2.IMREAD_GRAYSCALE)
    right = cv2.imread(str(d / "right.png"), cv2.IMREAD_GRAYSCALE)
    gt = cv2.imread(str(d / "disp_left.tif"), cv2.IMREAD_UNCHANGED)
    # the pair has no metric calibration: any f, b give the same disparities; d_max = fb/0.3 = 150 px
    rig = RectifiedStereo(450.0, 225.0, 187.0, 0.1, left.shape[1], left.shape[0])
    return left, right, gt, rig


def test_distances_match_reference(rng):
    a = rng.integers(0, 256, (20, 32), dtype=np.uint8)
    b = rng.integers(0, 256, (15, 32), dtype=np.uint8)
    ref = np.unpackbits(a[:, None] ^ b[None], axis=2).sum(2)
    np.testing.assert_array_equal(distance_matrix(a, b, True), ref)
    np.testing.assert_array_equal(pair_distances(a[:15], b, True), ref[np.arange(15), np.arange(15)])
    fa = normalise_descriptors(rng.normal(size=(20, 64)), False)
    fb = normalise_descriptors(rng.normal(size=(15, 64)), False)
    ref_f = np.linalg.norm(fa[:, None] - fb[None], axis=2)
    np.testing.assert_allclose(distance_matrix(fa, fb, False), ref_f, atol=FLOAT32_ARITH_TOL)


def test_ratio_and_cross_check_by_hand():
    # left 0: best right 0 (1.0) vs 2nd 3.0 -> ratio ok; left 1: 2.0 vs 2.1 -> ratio fails;
    # left 2: lone candidate right 1 at 5.0 (> max_single 4) -> rejected;
    # left 3: best right 0 at 0.5 (beats left 0) -> left 0 loses the cross-check
    i = np.array([0, 0, 1, 1, 2, 3])
    j = np.array([0, 2, 2, 3, 1, 0])
    d = np.array([1.0, 3.0, 2.0, 2.1, 5.0, 0.5])
    sel, st = ratio_and_cross_check(i, j, d, 4, 0.8, 4.0)
    assert sorted(zip(i[sel].tolist(), j[sel].tolist())) == [(3, 0)]
    assert st["ratio_rejected"] == 1 and st["single_rejected"] == 1 and st["cross_rejected"] == 1
    sel, _ = ratio_and_cross_check(i, j, d, 4, 0.8, 4.0, cross_check=False)
    assert sorted(zip(i[sel].tolist(), j[sel].tolist())) == [(0, 0), (3, 0)]


def _ratio_cross_reference(i, j, d, n_j, ratio, max_single, cross_check):
    """Per-feature loop: best = smallest distance, earliest pair on ties (the vectorised contract)."""
    keep = []
    for li in np.unique(i):
        idx = np.flatnonzero(i == li)
        best = idx[np.argmin(d[idx])]  # argmin returns the first of equal minima
        rest = np.delete(d[idx], np.flatnonzero(idx == best)[0])
        ok = d[best] < ratio * rest.min() if rest.size else d[best] <= max_single
        if ok:
            keep.append(best)
    keep = np.array(keep, np.int64)
    if cross_check:
        best_of_j = {int(jj): np.flatnonzero(j == jj)[np.argmin(d[j == jj])] for jj in np.unique(j)}
        keep = keep[[best_of_j[int(j[k])] == k for k in keep]].astype(np.int64)
    return keep


@pytest.mark.parametrize("grouped", [True, False])
def test_ratio_and_cross_check_matches_loop_reference(rng, grouped):
    # integer distances make ties common (Hamming), float ones make them rare (SIFT/SURF)
    for trial in range(40):
        p = int(rng.integers(1, 600))
        i = rng.integers(0, 60, p)
        j = rng.integers(0, 40, p)
        if grouped:
            i = np.sort(i)
        d = rng.integers(0, 12, p).astype(np.float32) if trial % 2 else rng.random(p).astype(np.float32)
        for cc in (True, False):
            sel, _ = ratio_and_cross_check(i, j, d, 40, 0.8, 6.0, cc)
            ref = _ratio_cross_reference(i, j, d, 40, 0.8, 6.0, cc)
            np.testing.assert_array_equal(np.sort(sel), np.sort(ref))


def test_binary_distance_matrix_chunks_and_odd_widths(rng):
    for dim in (32, 5):
        a = rng.integers(0, 256, (37, dim), dtype=np.uint8)
        b = rng.integers(0, 256, (23, dim), dtype=np.uint8)
        ref = np.unpackbits(a[:, None] ^ b[None], axis=2).sum(2)
        np.testing.assert_array_equal(distance_matrix(a, b, True), ref)
        np.testing.assert_array_equal(distance_matrix(a, b, True, chunk_bytes=64), ref)


def _features(xy: np.ndarray, lap: np.ndarray | None = None) -> Features:
    n = xy.shape[0]
    return Features(
        xy.astype(np.float32),
        np.full(n, 10, np.float32),
        np.zeros(n, np.float32),
        np.ones(n, np.float32),
        np.zeros(n, np.int8) if lap is None else lap.astype(np.int8),
        np.zeros((n, 64), np.float32),
        False,
    )


def test_candidate_pairs_match_brute_force(rng):
    rig = RectifiedStereo(400.0, 320.0, 200.0, 0.1, 640, 400)  # d_max = 40/0.3 = 133 px
    L = _features(rng.uniform(0, [640, 400], (150, 2)), rng.choice([-1, 1], 150))
    R = _features(rng.uniform(0, [640, 400], (170, 2)), rng.choice([-1, 1], 170))
    p = StereoMatchParams()
    i, j = candidate_pairs(L, R, rig, p)
    got = set(zip(i.tolist(), j.tolist()))
    ref = set()
    for a in range(L.n):
        for b in range(R.n):
            d = L.xy[a, 0] - R.xy[b, 0]
            if abs(L.xy[a, 1] - R.xy[b, 1]) <= 2 and 5 <= d <= 40 / 0.3 and L.laplacian[a] == R.laplacian[b]:
                ref.add((a, b))
    assert got == ref and len(ref) > 0


def test_refine_disparity_recovers_subpixel_shift(rng):
    base = smooth_texture(rng, 120, 400)
    for shift in (7.25, 12.5, 20.8):
        # right image = left image shifted left by `shift` px (true disparity), by exact interpolation
        M = np.float32([[1, 0, -shift], [0, 1, 0]])  # right(x) = left(x + shift)
        right = cv2.warpAffine(base, M, (400, 120), flags=cv2.INTER_CUBIC)
        L8, R8 = np.clip(base, 0, 255).astype(np.uint8), np.clip(right, 0, 255).astype(np.uint8)
        xl = rng.uniform(60, 340, 200)
        yl = rng.uniform(10, 110, 200)
        d0 = shift + rng.uniform(-1.0, 1.0, 200)  # descriptor-level disparity, off by up to 1 px
        d, ok, edge, _ = refine_disparity(L8, R8, xl, yl, d0)
        assert ok.mean() > 0.95 and not edge.any()
        assert np.median(np.abs(d[ok] - shift)) < 0.1
        # a descriptor disparity 3.5 px off puts the photometric minimum outside the ±2 px window
        _, ok_far, edge_far, _ = refine_disparity(L8, R8, xl, yl, np.full(200, shift + 3.5))
        assert edge_far.mean() > 0.9 and not np.any(ok_far & edge_far)


def test_refinement_sigma_tells_how_well_the_disparity_is_placed():
    """The refinement's own σ_d (the cost's curvature against its minimum) follows the real
    error: a textured half and a flat half (12 % of the contrast) of one noisy pair; σ_d is the
    flat half's several times over, it is within a factor 2.5 of each half's RMS error, and the
    matches it calls sharp (σ_d ≤ 0.12 px, the disparity offset's gate) are."""
    rng = np.random.default_rng(7)
    base = smooth_texture(rng, 200, 400).astype(np.float64)
    base[100:] = 128 + 0.12 * (base[100:] - 128)
    shift = 9.3
    M = np.float32([[1, 0, -shift], [0, 1, 0]])
    right = cv2.warpAffine(base.astype(np.float32), M, (400, 200), flags=cv2.INTER_CUBIC).astype(np.float64)
    L8 = np.clip(base + rng.normal(0, 2.0, base.shape), 0, 255).astype(np.uint8)
    R8 = np.clip(right + rng.normal(0, 2.0, base.shape), 0, 255).astype(np.uint8)
    n = 600
    xl = rng.uniform(40, 360, n)
    yl = np.r_[rng.uniform(8, 92, n // 2), rng.uniform(108, 192, n // 2)]
    d, ok, _, sig = refine_disparity(L8, R8, xl, yl, np.full(n, np.rint(shift)))
    assert np.all(np.isfinite(sig[ok])) and np.all(np.isinf(sig[~ok]))
    err = np.abs(d - shift)
    med = []
    for half in (slice(0, n // 2), slice(n // 2, n)):
        o = ok[half]
        rms = float(np.sqrt(np.mean(err[half][o] ** 2)))
        med.append(float(np.median(sig[half][o])))
        assert rms / 2.5 < med[-1] < rms * 2.5
    assert med[1] > 3 * med[0]
    sharp = ok & (sig <= 0.12)
    assert sharp.sum() > n // 3 and np.sqrt(np.mean(err[sharp] ** 2)) < 0.1


def test_refined_disparity_leans_to_whole_pixels_by_hundredths_that_average_out():
    # a far point's disparity error from the parabola fit (docs/frontend.md "Short steps in open
    # terrain"): a rendered frame's ORB corners, its right image an ideal (Fourier) shift of it
    import drivers

    with drivers.open_camera("sim://?realtime=0&fps=30&seed=3") as cam:
        left = next(iter(cam.frames())).left
    kp = make_detector(DetectorParams()).detect(left)
    xl, yl = np.rint(kp.xy[:, 0]), np.rint(kp.xy[:, 1])
    inside = (xl > 20) & (xl < left.shape[1] - 20) & (yl > 10) & (yl < left.shape[0] - 10)
    xl, yl = xl[inside], yl[inside]
    freq = np.fft.fftfreq(left.shape[1])[None, :]
    spectrum = np.fft.fft(left.astype(np.float64), axis=1)
    bias = []
    for shift in np.arange(5.0, 5.95, 0.1):
        right = np.clip(np.rint(np.real(np.fft.ifft(spectrum * np.exp(2j * np.pi * freq * shift), axis=1))), 0, 255)
        d, ok, _, _ = refine_disparity(left, right.astype(np.uint8), xl, yl, np.full(xl.size, np.rint(shift)))
        assert ok.mean() > 0.95
        bias.append(float(np.mean(d[ok] - shift)))
    b = np.array(bias)
    assert np.abs(b).max() < 0.08  # towards whole pixels by a few hundredths at most
    assert b[2:5].mean() < -0.01 and b[6:9].mean() > 0.01  # short past a whole pixel, long before the next
    assert abs(b.mean()) < 0.02  # over a pixel of disparities it averages out


def test_stereo_middlebury_rows_disparity_and_depth(shared_data):
    left, right, gt, rig = _middlebury(shared_data)
    det = make_detector(DetectorParams(name="sift", max_features=1500))
    fl, fr = det.detect(left), det.detect(right)
    m = match_stereo(fl, fr, rig, StereoMatchParams(), left, right)
    assert m.n > 300
    # row constraint and positive disparity within bounds
    assert np.all(np.abs(fl.xy[m.left_idx, 1] - fr.xy[m.right_idx, 1]) <= 2.0)
    d = m.xl - m.xr
    assert np.all(d >= 5.0) and np.all(d <= rig.fb / 0.3)
    # triangulated depth against ground-truth disparity for most matches
    g = gt[np.rint(m.y).astype(int), np.rint(m.xl).astype(int)]
    ok = g > 0
    assert ok.mean() > 0.8
    X_gt = rig.fb / g[ok]
    rel = np.abs(m.xyz_R[ok, 0] - X_gt) / X_gt
    assert np.mean(rel < 0.05) > 0.9
    assert np.median(np.abs(d[ok] - g[ok])) < 0.25
    # covariances are symmetric positive definite
    assert np.all(np.linalg.eigvalsh(m.cov_R) > 0)


def test_patch_refinement_beats_orb_keypoints_on_middlebury(shared_data):
    left, right, gt, rig = _middlebury(shared_data)
    det = make_detector(DetectorParams(name="orb", max_features=1500))
    fl, fr = det.detect(left), det.detect(right)
    med = {}
    for ref in ("keypoint", "patch"):
        m = match_stereo(fl, fr, rig, StereoMatchParams(refine=ref), left, right)
        g = gt[np.rint(m.y).astype(int), np.rint(m.xl).astype(int)]
        ok = g > 0
        med[ref] = float(np.median(np.abs((m.xl - m.xr)[ok] - g[ok])))
    assert med["patch"] < 0.6 * med["keypoint"]


def test_stereo_bad_and_empty_inputs():
    rig = RectifiedStereo(400.0, 320.0, 200.0, 0.1, 640, 400)
    e = Features.empty(64)
    m = match_stereo(e, e, rig)
    assert m.n == 0 and m.xyz_R.shape == (0, 3) and m.cov_R.shape == (0, 3, 3)
    with pytest.raises(InputError, match="one detector"):
        match_stereo(_features(np.zeros((3, 2))), Features.empty(32, binary=True), rig)
    with pytest.raises(ConfigError, match="refine"):
        StereoMatchParams(refine="magic")


def test_debias_limits_moves_only_matches_near_the_gate(shared_data):
    left, right, _, rig = _middlebury(shared_data)
    det = make_detector(DetectorParams(name="sift", max_features=1500))
    fl, fr = det.detect(left), det.detect(right)
    # Middlebury is near: put the far limit where a tenth of its matches are
    d_all = match_stereo(fl, fr, rig, StereoMatchParams(), left, right)
    gate = float(np.quantile(d_all.xl - d_all.xr, 0.1))
    off = match_stereo(fl, fr, rig, StereoMatchParams(d_min_px=gate), left, right)
    on = match_stereo(fl, fr, rig, StereoMatchParams(d_min_px=gate, debias_limits=True), left, right)
    assert np.array_equal(off.left_idx, on.left_idx) and np.array_equal(off.right_idx, on.right_idx)
    d_off, d_on = off.xl - off.xr, on.xl - on.xr
    sigma_d = np.sqrt(2.0) * StereoMatchParams().sigma_x_px
    expected = gate_selection_shift(d_off, gate, rig.fb / 0.3, sigma_d)
    np.testing.assert_allclose(d_off - d_on, expected, atol=1e-9)
    np.testing.assert_allclose(0.5 * (on.xl + on.xr), 0.5 * (off.xl + off.xr), atol=1e-9)  # on its ray
    assert np.sum(expected > 0.1) >= 5  # the matches near the far limit moved
    inside = (d_off > gate + 6 * sigma_d) & (d_off < rig.fb / 0.3 - 6 * sigma_d)  # far from both limits
    assert inside.sum() > 100
    np.testing.assert_allclose(on.xyz_R[inside], off.xyz_R[inside], rtol=1e-6)
