"""The front end's stages are timed as the step's are: each a method decorated with its stage's
name (robotd.core.timing.stage), ``Frontend.process`` a list of plain calls (issue 28, item 5)."""

from __future__ import annotations

import inspect

import numpy as np

import drivers
from robotd.core.timing import StageClock
from robotd.frontend.frontend import Frontend

STAGES = {"detect": "detect", "match_stereo": "stereo", "identify": "identify", "screen": "outliers"}
STAGES["visual_motion"] = "motion"


def test_the_front_ends_stages_are_decorated_methods() -> None:
    assert {name: getattr(Frontend, name).stage_name for name in STAGES} == STAGES
    source = inspect.getsource(Frontend.process)
    assert ".run(" not in source and not hasattr(StageClock, "run")


def test_process_reports_every_stage_in_order_and_the_total() -> None:
    with drivers.open_camera("sim://?realtime=0&fps=10&seed=5") as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(2)]
        rig = cam.rectified_model()
    fe = Frontend(rig, rng=np.random.default_rng(0))
    for f in frames:
        r = fe.process(f.left, f.right, f.t_ns)
        assert list(r.timings_ms) == ["detect", "stereo", "identify", "outliers", "motion", "total"]
        assert all(v >= 0.0 for v in r.timings_ms.values())
        assert r.timings_ms["total"] >= sum(v for k, v in r.timings_ms.items() if k != "total")
    assert r.counts["inliers"] > 0  # the second frame identified the first one's landmarks
