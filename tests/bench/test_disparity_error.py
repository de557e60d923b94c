"""bench/disparity_error.py: the true disparity it compares against, its test for a patch on one
plane, and one JSON object with the table's bins."""

from __future__ import annotations

import json
from types import ModuleType

import numpy as np
import pytest

from tests.support.paths import load_bench


def _bench() -> ModuleType:
    return load_bench("disparity_error")


def test_true_disparity_is_exact_on_a_plane_and_edges_are_told_apart() -> None:
    bench = _bench()
    ys, xs = np.mgrid[0:40, 0:60].astype(float)
    iz = 0.01 + 0.002 * xs + 0.001 * ys  # a plane: inverse depth affine in the pixel
    depth = 1.0 / iz
    x, y = np.array([10.3, 30.7]), np.array([12.6, 20.2])
    assert np.allclose(bench.true_disparity(depth, x, y, 100.0), 100.0 * (0.01 + 0.002 * x + 0.001 * y))
    assert bench.patch_on_one_surface(depth, x, y, 3).all()
    step = depth.copy()
    step[:, 31:] *= 3.0  # a farther surface from column 31 on
    step[:5] = np.inf  # and sky along the top
    on = bench.patch_on_one_surface(step, np.array([10.0, 30.0, 45.0, 20.0]), np.array([20.0, 20.0, 20.0, 6.0]), 3)
    assert on.tolist() == [True, False, True, False]


def test_it_prints_one_json_object_with_every_bin(capsys: pytest.CaptureFixture[str]) -> None:
    bench = _bench()
    url = "sim://?world=open_terrain&speed=5&fps=5&realtime=0&width=320&height=200"
    assert bench.main(["--url", url, "--frames", "2", "--step", "30", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["matches"] > 50 and res["fb_px_m"] == pytest.approx(0.9 * 215.0)
    assert [b["bin_px"] for b in res["bins"]] == [[0, 3], [3, 5], [5, 10], [10, 20], [20, None]]
    assert sum(b["all"]["n"] for b in res["bins"]) == res["matches"]
    assert [b["kept_by_default"] for b in res["bins"]] == [False, True, True, True, True]
    with pytest.raises(SystemExit):
        bench.main(["--url", "kitti:///nowhere"])
