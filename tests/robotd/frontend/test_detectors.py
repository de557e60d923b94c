"""Detectors (docs/math.md §4.1): the common interface, input errors, grid bucketing."""

from __future__ import annotations

import numpy as np
import pytest

from robotd.core.errors import ConfigError, InputError
from robotd.frontend.detectors import DetectorParams, bucket_select, make_detector, surf_available
from tests.support.images import smooth_texture

DETECTORS = ["orb", "sift", pytest.param("surf", marks=pytest.mark.skipif(not surf_available(), reason="no SURF"))]


@pytest.mark.parametrize("name", DETECTORS)
def test_detector_interface(name, rng):
    img = np.clip(smooth_texture(rng, 240, 320), 0, 255).astype(np.uint8)
    det = make_detector(DetectorParams(name=name, max_features=300))
    f = det.detect(img)
    assert 0 < f.n <= 300
    assert f.xy.shape == (f.n, 2) and f.desc.shape[0] == f.n
    assert f.binary == (name == "orb") == det.binary
    assert f.desc.dtype == (np.uint8 if name == "orb" else np.float32)
    assert np.all((f.xy >= 0) & (f.xy < [320, 240]))
    assert det.detect(img, max_features=50).n <= 50
    # featureless and empty images give empty feature sets, not crashes
    assert det.detect(np.zeros((240, 320), np.uint8)).n == 0
    assert det.detect(np.zeros((0, 0), np.uint8)).n == 0


def test_detector_bad_inputs():
    with pytest.raises(ConfigError, match="frontend.detector.name"):
        DetectorParams(name="akaze")
    with pytest.raises(ConfigError, match="max_features"):
        DetectorParams(max_features=0)
    det = make_detector(DetectorParams())
    with pytest.raises(InputError, match="uint8"):
        det.detect(np.zeros((10, 10), np.float32))
    with pytest.raises(InputError, match="2-D"):
        det.detect(np.zeros((4, 10, 10), np.uint8))


def test_surf_missing_gives_clear_error(monkeypatch):
    import sys

    import robotd.frontend

    monkeypatch.setitem(sys.modules, "robotd.frontend.surf", None)  # import now raises ImportError
    monkeypatch.delattr(robotd.frontend, "surf", raising=False)
    with pytest.raises(ConfigError, match="surf"):
        make_detector(DetectorParams(name="surf"))


def test_bucketing_spreads_and_caps(rng):
    # 2000 features, 90 % of them crowded into one corner with high responses
    xy = np.r_[rng.uniform(0, 50, (1800, 2)), rng.uniform(0, [640, 400], (200, 2))].astype(np.float32)
    resp = np.r_[rng.uniform(10, 20, 1800), rng.uniform(0, 1, 200)].astype(np.float32)
    keep = bucket_select(xy, resp, (400, 640), 256, 4, 8)
    assert keep.size == 256 and np.unique(keep).size == 256
    col = np.minimum((xy[keep, 0] * 8 / 640).astype(int), 7)
    row = np.minimum((xy[keep, 1] * 4 / 400).astype(int), 3)
    cells = np.unique(row * 8 + col)
    assert cells.size >= 28  # nearly every cell is represented
    # within a cell the strongest are kept: the quota is 8 per cell
    in_corner = keep[(xy[keep, 0] < 50) & (xy[keep, 1] < 50)]
    assert np.min(resp[in_corner]) >= np.sort(resp[:1800])[-in_corner.size]


def test_bucketing_matches_per_cell_loop_reference(rng):
    # ties in the response (quantised) exercise the stable order: earlier features win
    h, w, rows, cols, cap = 400, 640, 4, 8, 300
    xy = rng.uniform(0, [w, h], (2000, 2)).astype(np.float32)
    resp = np.round(rng.gamma(2.0, 1.0, 2000), 1).astype(np.float32)
    cell = np.minimum((xy[:, 1] * rows / h).astype(int), rows - 1) * cols + np.minimum(
        (xy[:, 0] * cols / w).astype(int), cols - 1
    )
    quota = -(-cap // (rows * cols))
    first, rest = [], []
    for c in range(rows * cols):
        members = [k for k in np.argsort(-resp, kind="stable") if cell[k] == c]
        first += members[:quota]
        rest += members[quota:]
    first_a = np.array(first)
    if first_a.size >= cap:
        ref = first_a[np.argsort(-resp[first_a], kind="stable")[:cap]]
    else:
        rest_a = np.array(rest)
        ref = np.r_[first_a, rest_a[np.argsort(-resp[rest_a], kind="stable")[: cap - first_a.size]]]
    got = bucket_select(xy, resp, (h, w), cap, rows, cols)
    assert sorted(got.tolist()) == sorted(ref.tolist())
    assert np.all(np.diff(resp[got]) <= 0)  # strongest first
