"""The front end's numba kernels compute what their numpy references compute.

Inputs: random ones with many ties (integer distances), and a rendered sim:// pair with its ORB
features, the daemon's own workload.
"""

from __future__ import annotations

import numpy as np
import pytest

import drivers
from robotd.frontend.detectors import DetectorParams, make_detector
from robotd.frontend.stereo_match import (
    StereoMatchParams,
    candidate_pairs,
    match_stereo,
    mutual_matches,
    normalise_descriptors,
    pair_distances,
    ratio_and_cross_check,
    refine_disparity,
    window_pairs,
)
from tests.support.reference_frontend import (
    mutual_matches_numpy,
    ratio_and_cross_check_numpy,
    refine_disparity_numpy,
    window_pairs_numpy,
)


@pytest.fixture(scope="module")
def sim_pair():
    with drivers.open_camera("sim://?realtime=0&fps=30") as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(3)]
        rig = cam.rectified_model()
    det = make_detector(DetectorParams())
    f = frames[-1]
    return f.left, f.right, det.detect(f.left), det.detect(f.right), rig


@pytest.mark.parametrize("grouped", [True, False])
def test_ratio_cross_kernel_equals_numpy(rng, grouped):
    for trial in range(60):
        p = int(rng.integers(1, 800))
        i = rng.integers(0, 80, p)
        j = rng.integers(0, 50, p)
        if grouped:
            i = np.sort(i)
        if trial % 3 == 0:
            d = rng.integers(0, 10, p).astype(np.float32)  # Hamming-like: ties everywhere
        elif trial % 3 == 1:
            d = rng.random(p).astype(np.float32)
        else:
            d = rng.random(p)  # float64 input keeps its precision
        for cc in (True, False):
            got, st = ratio_and_cross_check(i, j, d, 50, 0.8, 0.45 if trial % 3 else 6.0, cc)
            ref, st_ref = ratio_and_cross_check_numpy(i, j, d, 50, 0.8, 0.45 if trial % 3 else 6.0, cc)
            np.testing.assert_array_equal(got, ref)  # same pairs, same order
            assert st == st_ref


def _near_copies(rng, n, m, width, flip):
    """(n, width) random binary descriptors and (m, width) ones of which some are noisy copies,
    some exact duplicates of each other (ties in rows and columns) and the rest random."""
    a = rng.integers(0, 256, (n, width), dtype=np.uint8)
    b = rng.integers(0, 256, (m, width), dtype=np.uint8)
    k = min(n, m) * 2 // 3
    if k:
        src = rng.choice(n, k, replace=False)
        bits = np.unpackbits(a[src], axis=1) ^ (rng.random((k, width * 8)) < flip)
        b[:k] = np.packbits(bits, axis=1)
        if m > 4:
            b[k // 2 :: 7] = b[k // 2]  # repeated rows: equal distances everywhere in their columns
        if n > 4:
            # near copies of one row: they compete for the same column (the cross-check decides)
            rows = np.arange(k // 3, n, 11)
            bits = np.unpackbits(np.repeat(a[k // 3 : k // 3 + 1], rows.size, 0), axis=1)
            a[rows] = np.packbits(bits ^ (rng.random(bits.shape) < flip / 2), axis=1)
    return a, b


def test_mutual_binary_kernel_equals_numpy(rng):
    """The one-pass kernel gives the pairs the distance matrix did, in the same order, for every
    ratio, limit and mode, with ties, a single column and empty sets."""
    checked = 0
    for trial in range(40):
        n, m = int(rng.integers(0, 120)), int(rng.integers(0, 120))
        if trial % 10 == 0:
            m = 1
        a, b = _near_copies(rng, n, m, 32, (0.02, 0.1, 0.2)[trial % 3])
        for max_d in (20.0, 60.0, 60.5, 90.0):
            for ratio in (0.6, 0.75, 0.8, 0.9):  # at 0.6 float32 and float64 products differ
                for second_in_row in (True, False):
                    got = mutual_matches(a, b, True, max_d, ratio, second_in_row)
                    ref = mutual_matches_numpy(a, b, True, max_d, ratio, second_in_row)
                    np.testing.assert_array_equal(got[0], ref[0])
                    np.testing.assert_array_equal(got[1], ref[1])
                    assert got[0].dtype == got[1].dtype == np.int64
                    checked += got[0].size
    assert checked > 1000  # the cases were not all empty


def _same_pairs(a, b, binary, max_d, ratio, at_least):
    """mutual_matches and its numpy twin agree (pairs and order) in both modes, on enough pairs."""
    for second_in_row in (True, False):
        got = mutual_matches(a, b, binary, max_d, ratio, second_in_row)
        ref = mutual_matches_numpy(a, b, binary, max_d, ratio, second_in_row)
        np.testing.assert_array_equal(np.c_[got], np.c_[ref])
        assert got[0].size > at_least


def test_mutual_matches_other_descriptors_equal_numpy(rng):
    # binary widths that are not whole 64-bit words, and float descriptors, take the matrix path
    a, b = _near_copies(rng, 90, 70, 20, 0.05)
    _same_pairs(a, b, True, 40.0, 0.75, 20)
    fa = normalise_descriptors(rng.normal(size=(80, 64)), False)
    fb = normalise_descriptors(np.r_[fa[:50] + rng.normal(0, 0.05, (50, 64)), rng.normal(size=(30, 64))], False)
    _same_pairs(fa, fb, False, 0.7, 0.8, 20)


def test_mutual_matches_on_rendered_frames():
    """The daemon's workload: ORB features of two simulated frames 0.2 s apart."""
    det = make_detector(DetectorParams())
    with drivers.open_camera("sim://?realtime=0&fps=30") as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(7)]
    fa, fb = det.detect(frames[0].left), det.detect(frames[6].left)
    _same_pairs(normalise_descriptors(fb.desc, True), normalise_descriptors(fa.desc, True), True, 60.0, 0.75, 50)


def test_window_pairs_kernel_equals_numpy(rng):
    """Guided identification's window: the same pairs in the same order as the three masks, with
    distances of exactly r everywhere (pixels on a quarter-pixel grid), ties in the sorted
    columns, NaN and inf predictions, and rows ignored."""
    seen = 0
    for trial in range(60):
        n, k = int(rng.integers(0, 150)), int(rng.integers(0, 300))
        px = np.round(rng.uniform(0, 120, (n, 3)) * 4) / 4
        px[:, 1] = px[:, 0] - np.round(rng.uniform(1, 30, n) * 4) / 4
        pred = np.round(rng.uniform(-10, 130, (k, 3)) * 4) / 4
        pred[:, 1] = pred[:, 0] - np.round(rng.uniform(0, 32, k) * 4) / 4
        if k > 3 and trial % 4 == 0:
            pred[::3, 0] = pred[0, 0]  # equal columns: the stable sort's ties
            pred[1] = np.nan
            pred[2, 0] = np.inf
        if n > 2 and trial % 5 == 0:
            px[1, 0] = np.nan
        for r in (0.25, 5.0, 15.0):
            for rows_known in (True, False):
                got = window_pairs(px, pred, r, rows_known)
                ref = window_pairs_numpy(px, pred, r, rows_known)
                np.testing.assert_array_equal(np.c_[got], np.c_[ref])
                seen += got[0].size
    assert seen > 10_000


def test_refine_kernel_equals_numpy_on_random_points(rng, sim_pair):
    left, right, *_ = sim_pair
    h, w = left.shape
    n = 3000
    # includes points whose patch or search window leaves the image (skipped by both)
    xl = rng.uniform(-2, w + 2, n)
    yl = rng.uniform(-2, h + 2, n)
    d0 = rng.uniform(0, 80, n)
    for half, search in ((3, 2), (2, 3)):
        d, ok, edge, sig = refine_disparity(left, right, xl, yl, d0, half, search)
        d_r, ok_r, edge_r, sig_r = refine_disparity_numpy(left, right, xl, yl, d0, half, search)
        np.testing.assert_array_equal(ok, ok_r)
        np.testing.assert_array_equal(edge, edge_r)
        np.testing.assert_array_equal(d, d_r)  # integer costs: bit-identical
        np.testing.assert_allclose(sig, sig_r, rtol=1e-12)  # inf where not refined, in both
        assert np.all(np.isfinite(sig[ok])) and np.all(np.isinf(sig[~ok]))
        assert ok.sum() > 100 and edge.sum() > 100


def test_match_stereo_on_rendered_pair(sim_pair):
    left, right, fl, fr, rig = sim_pair
    p = StereoMatchParams()
    i, j = candidate_pairs(fl, fr, rig, p)
    assert i.size > fl.n  # several candidates per feature
    assert np.all(np.diff(i) >= 0)  # grouped by left feature: the matcher's fast path relies on it
    # every pair obeys the row band and disparity range
    d_min, d_max = rig.disparity_bounds(p.depth_min_m, p.d_min_px)
    assert np.all(np.abs(fl.xy[i, 1] - fr.xy[j, 1]) <= p.row_tol_px)
    dx = fl.xy[i, 0].astype(np.float64) - fr.xy[j, 0]
    assert np.all((dx >= d_min) & (dx <= d_max))
    dist = pair_distances(fl.desc[i], fr.desc[j], True)
    sel, _ = ratio_and_cross_check(i, j, dist, fr.n, 0.75, p.max_single_binary)
    sel_r, _ = ratio_and_cross_check_numpy(i, j, dist, fr.n, 0.75, p.max_single_binary)
    np.testing.assert_array_equal(sel, sel_r)
    m = match_stereo(fl, fr, rig, p, left, right)
    assert m.n > 300 and m.refined.mean() > 0.9


def test_bucket_kernel_equals_numpy(rng):
    from robotd.frontend.detectors import bucket_select
    from tests.support.reference_frontend import bucket_select_numpy

    for trial in range(80):
        n = int(rng.integers(1, 5000))
        xy = rng.uniform(0, [640, 400], (n, 2)).astype(np.float32)
        if trial % 4 == 0:
            xy[: n // 2] = rng.uniform(0, [100, 80], (n // 2, 2))  # crowded corner: sparse cells elsewhere
        # FAST scores are small integers: ties everywhere; SIFT/SURF responses are floats
        resp = rng.integers(0, 30, n).astype(np.float32) if trial % 2 else rng.random(n).astype(np.float32)
        cap = int(rng.integers(1, 1500))
        rows, cols = (4, 8) if trial % 3 else (int(rng.integers(1, 7)), int(rng.integers(1, 9)))
        got = bucket_select(xy, resp, (400, 640), cap, rows, cols)
        ref = bucket_select_numpy(xy, resp, (400, 640), cap, rows, cols)
        np.testing.assert_array_equal(got, ref)


def test_warmup_compiles_every_signature_the_pipeline_uses():
    # the daemon warms the kernels at start-up: its frames must not trigger a compile
    from robotd.config import load_config
    from robotd.core import _outlier_kernels, outliers
    from robotd.frontend import _align_kernels, _detect_kernels, _stereo_kernels, align, detectors, stereo_match
    from robotd.pipeline.step import Pipeline

    kernels = [
        _detect_kernels.bucket_kernel,
        _stereo_kernels.candidate_pairs_kernel,
        _stereo_kernels.ratio_cross_kernel,
        _stereo_kernels.refine_kernel,
        _stereo_kernels.mutual_binary_kernel,
        _stereo_kernels.window_pairs_kernel,
        _align_kernels.align_kernel,
        _outlier_kernels.similarity_d2_kernel,
        _outlier_kernels.gn_weights,
        _outlier_kernels.gn_fit,
    ]
    detectors.warmup()
    stereo_match.warmup()
    align.warmup()
    outliers.warmup()
    before = [set(k.signatures) for k in kernels]
    cfg = load_config(None, {"camera": {"url": "sim://?realtime=0"}, "vehicle": {"url": "sim://?realtime=0"}})
    with drivers.open_camera("sim://?realtime=0&fps=30") as cam:
        pipe = Pipeline(cfg, cam.rectified_model(), np.random.default_rng(0))
        it = cam.frames()
        for _ in range(4):  # the first frame starts the map; the next ones identify against it
            pipe.step(next(it), None)
    after = [set(k.signatures) for k in kernels]
    assert after == before, [a - b for a, b in zip(after, before, strict=True)]


def test_kernel_wrappers_refuse_inputs_the_kernels_would_read_past():
    # the kernels have no bounds checks: the wrappers must say what is wrong instead
    from robotd.core.errors import InputError
    from robotd.core.outliers import fit_similarity_mahalanobis, similarity_d2

    i, j, d = np.array([0, 0, 1]), np.array([0, 5, 1]), np.ones(3, np.float32)
    with pytest.raises(InputError, match="0 <= j < n_j = 4"):
        ratio_and_cross_check(i, j, d, 4, 0.8, 60.0)
    with pytest.raises(InputError, match="one length"):
        ratio_and_cross_check(i, j[:2], d, 8, 0.8, 60.0)
    img = np.zeros((20, 40), np.uint8)
    with pytest.raises(InputError, match="one length"):
        refine_disparity(img, img, np.ones(3), np.ones(2), np.ones(3))
    with pytest.raises(InputError, match="mutual_matches: expected .* of one width"):
        mutual_matches(np.zeros((3, 32), np.uint8), np.zeros((4, 16), np.uint8), True, 60.0, 0.75, True)
    with pytest.raises(InputError, match="mutual_matches: expected"):
        mutual_matches(np.zeros(32, np.uint8), np.zeros((4, 32), np.uint8), True, 60.0, 0.75, True)
    with pytest.raises(InputError, match=r"window_pairs: expected \(N, 3\) and \(K, 3\)"):
        window_pairs(np.zeros((4, 2)), np.zeros((3, 3)), 15.0)
    a = np.zeros((5, 3))
    with pytest.raises(InputError, match="similarity_d2"):
        similarity_d2(np.ones(2), np.eye(3)[None], np.zeros((2, 3)), a, a, None, np.eye(3)[None].repeat(5, 0))
    with pytest.raises(InputError, match="expected B of shape"):
        fit_similarity_mahalanobis(a, a, None, np.eye(3)[None].repeat(4, 0), 1.0, np.eye(3), np.zeros(3))
