"""The stage list docs/architecture.md documents is the one ``Pipeline.step`` runs.

The document holds it as one line between ``<!-- stages -->`` markers, stages in order and the
optional ones in parentheses. It is compared with the stage methods (``robotd.core.timing.stage``, on
the objects of robotd/pipeline/stages/) that the source of ``Pipeline.step`` calls and with the stages a
real step on the simulated rover timed (``StepResult.timings_ms`` keeps them in the order the clock
saw them), so a stage added to, moved in or renamed in the step without the document fails here.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
import textwrap

import numpy as np
import pytest

import drivers
import robotd.pipeline.stages
from robotd.config import load_config
from robotd.core.stereo import RectifiedStereo
from robotd.pipeline import relocalise
from robotd.pipeline.step import Pipeline
from tests.support.paths import REPO

DOC = REPO / "docs" / "architecture.md"
RIG = RectifiedStereo(700.0, 320.0, 200.0, 0.12, 640, 400)


def documented_stages() -> list[tuple[str, bool]]:
    """(name, optional) of each stage, in the documented order."""
    text = DOC.read_text(encoding="utf-8")
    m = re.search(r"<!-- stages -->\s*`([^`]*)`\s*<!-- /stages -->", text)
    assert m, f"{DOC}: no stage line between <!-- stages --> and <!-- /stages -->"
    out: list[tuple[str, bool]] = []
    for part in m.group(1).split("→"):
        part = part.strip()
        opt = re.fullmatch(r"\((\w+)\)", part)
        assert opt or re.fullmatch(r"\w+", part), f"{DOC}: cannot read the stage {part!r}"
        out.append((opt.group(1), True) if opt else (part, False))
    names = [n for n, _ in out]
    assert len(names) == len(set(names)), f"{DOC}: a stage is listed twice: {names}"
    return out


def stage_methods() -> dict[str, str]:
    """Qualified name -> stage name of every stage method of robotd/pipeline/stages/ (a method decorated
    with ``robotd.core.timing.stage``)."""
    out: dict[str, str] = {}
    for info in pkgutil.iter_modules(robotd.pipeline.stages.__path__):
        module = importlib.import_module(f"robotd.pipeline.stages.{info.name}")
        for cls in vars(module).values():
            if isinstance(cls, type) and cls.__module__ == module.__name__:
                for fn in vars(cls).values():
                    if hasattr(fn, "stage_name"):
                        out[fn.__qualname__] = fn.stage_name
    return out


def _pipeline_attr(node: ast.expr) -> str | None:
    """``x`` of the expression ``self.x``, else None."""
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "self":
        return node.attr
    return None


def stages_in_source() -> list[str]:
    """The stages ``Pipeline.step`` calls, in source order: the calls of a stage method on one of
    the pipeline's objects, ``self.gap.across(...)``, or through a local name bound to one
    (``fe = self.measure``; ``fe.detect(frame)``)."""
    p = Pipeline(load_config(None), RIG, np.random.default_rng(0))
    tree = ast.parse(textwrap.dedent(inspect.getsource(Pipeline.step)))
    bound: dict[str, str] = {}  # local name -> the pipeline's attribute bound to it
    for n in ast.walk(tree):
        if isinstance(n, ast.Assign) and len(n.targets) == 1:
            target, value = n.targets[0], n.value
            pairs = (
                zip(target.elts, value.elts)
                if isinstance(target, ast.Tuple) and isinstance(value, ast.Tuple)
                else [(target, value)]
            )
            bound |= {t.id: a for t, v in pairs if isinstance(t, ast.Name) and (a := _pipeline_attr(v))}
    calls = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute):
            recv = n.func.value
            attr = bound.get(recv.id) if isinstance(recv, ast.Name) else _pipeline_attr(recv)
            fn = getattr(type(getattr(p, attr)), n.func.attr, None) if attr else None
            if hasattr(fn, "stage_name"):
                calls.append((n.lineno, n.col_offset, fn.stage_name))
    return [name for *_, name in sorted(calls)]


def check_order(timed: list[str], doc: list[tuple[str, bool]]) -> list[str]:
    """What is wrong with one step's timed stages (``total`` left out) against the documented
    list: a stage not documented, stages out of the documented order, a required stage missing.
    A step that ended at ``relocalise`` (the map not found yet) times nothing after it."""
    names = [n for n, _ in doc]
    bad = [f"stage {s!r} is timed but not documented" for s in timed if s not in names]
    if bad:
        return bad
    if timed != sorted(timed, key=names.index):
        return [f"timed in the order {timed}, documented {names}"]
    last = names.index("relocalise") if timed and timed[-1] == "relocalise" else len(names) - 1
    return [f"required stage {n!r} was not timed" for n, opt in doc[: last + 1] if not opt and n not in timed]


def test_the_documented_stages_are_the_ones_in_the_source() -> None:
    assert [n for n, _ in documented_stages()] == stages_in_source()


STEP_MAX_LINES = 45  # issue 28: a screenful; docs/architecture.md "Data flow"


def test_the_step_calls_every_stage_and_no_clock() -> None:
    """Every stage method of robotd/pipeline/stages/ is called by the step, and the step only starts
    the clock: it wraps nothing in it, its calls are the stages' own."""
    assert sorted(stages_in_source()) == sorted(set(stage_methods().values()))
    tree = ast.parse(textwrap.dedent(inspect.getsource(Pipeline.step)))
    names = [ast.unparse(n) for n in ast.walk(tree) if isinstance(n, ast.Name | ast.Attribute)]
    uses = [name for name in names if "clock" in name]
    assert sorted(uses) == ["self.clock", "self.clock.start"], uses


def test_the_step_is_a_screenful() -> None:
    """``Pipeline.step`` reads as a screenful of plain calls; the choices between stages are named methods."""
    n = len(inspect.getsource(Pipeline.step).splitlines())
    assert n <= STEP_MAX_LINES, f"Pipeline.step is {n} lines: move a choice between stages into a named method"


PIPELINE_MAX_LINES = 300  # issue 28: the stages live in robotd/pipeline/stages/, the Pipeline wires them


def test_the_pipeline_class_stays_small() -> None:
    n = len(inspect.getsource(Pipeline).splitlines())
    assert n <= PIPELINE_MAX_LINES, (
        f"Pipeline is {n} lines: move a cohesive group of methods into robotd/pipeline/stages/"
    )


def test_the_order_check_catches_what_it_is_for() -> None:
    doc = [("a", False), ("b", True), ("relocalise", True), ("c", False)]
    assert check_order(["a", "b", "relocalise", "c"], doc) == []
    assert check_order(["a", "c"], doc) == []  # optional ones absent
    assert check_order(["a", "relocalise"], doc) == []  # the step ended at relocalise
    assert check_order(["a", "x", "c"], doc)  # undocumented
    assert check_order(["a", "c", "b"], doc)  # out of order
    assert check_order(["a", "b"], doc)  # a required one missing


@pytest.fixture(scope="module")
def sim() -> tuple[list, object]:
    with drivers.open_camera("sim://?realtime=0&fps=30&seed=3") as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(41)]
        rig = cam.rectified_model()
    return frames, rig


def test_a_real_step_times_the_documented_stages_in_order(sim) -> None:
    frames, rig = sim
    doc = documented_stages()
    cfg = load_config(None, {"slam": {"n_particles": 20}})
    seen: list[list[str]] = []

    def step(p: Pipeline, frame) -> None:
        r = p.step(frame, None)
        keys = list(r.timings_ms)
        assert keys[-1] == "total", keys
        seen.append(keys[:-1])

    p = Pipeline(cfg, rig, np.random.default_rng(1))
    for f in frames[:12]:
        step(p, f)
    # a gap no odometry covers: 0.8 s of frames never reach the step
    assert (frames[36].t_ns - frames[11].t_ns) * 1e-9 > 0.6
    for f in frames[36:38]:
        step(p, f)
    # a map loaded: the next frames relocalise in it
    q = Pipeline(cfg, rig, np.random.default_rng(2))
    q.load_state_dict(p.state_dict())
    for f in frames[38:40]:
        step(q, f)
    # a relocalising window that ended without a fix: the search looks for the loaded map
    q.relocaliser.frames_left, q.relocaliser.search_left = 0, relocalise.SEARCH_EVERY + 1
    step(q, frames[40])
    bad = [f"step {i}: {msg}" for i, keys in enumerate(seen) for msg in check_order(keys, doc)]
    assert not bad, "\n".join(bad)
    # every documented stage, the optional ones included, was seen at least once
    timed = {s for keys in seen for s in keys}
    assert timed == {n for n, _ in doc}, sorted({n for n, _ in doc} - timed)


def test_new_landmarks_nearest_or_spread_over_depth_when_the_map_is_not_reobserved():
    """slam.new_landmarks: "nearest" keeps the k most precise new measurements; "adaptive" does the
    same while the frame re-observed the map, and spreads the k over the precision ranks (near to
    far) in a frame that re-observed fewer than ADAPTIVE_MIN_REOBSERVED landmarks."""
    from types import SimpleNamespace

    from robotd.pipeline.stages.measure import ADAPTIVE_MIN_REOBSERVED, Measure

    rng = np.random.default_rng(4)
    sig = rng.permutation(np.arange(1, 101, dtype=float))  # 100 measurements, precisions shuffled
    meas = SimpleNamespace(cov_R=sig[:, None, None] * np.eye(3))
    new = np.arange(100)
    rank = np.argsort(np.argsort(sig))  # 0 = most precise

    def pick(policy: str, reobserved: int) -> np.ndarray:
        me = SimpleNamespace(cfg=load_config(None, {"slam": {"new_landmarks": policy}}))
        out = Measure._pick_new(me, meas, new, 10, reobserved)  # type: ignore[arg-type]
        assert np.all(np.diff(out) > 0) and out.size == 10
        return rank[out]

    nearest = set(range(10))
    assert set(pick("nearest", 0)) == nearest
    assert set(pick("adaptive", ADAPTIVE_MIN_REOBSERVED)) == nearest
    spread = np.sort(pick("adaptive", ADAPTIVE_MIN_REOBSERVED - 1))
    assert spread[0] == 0 and spread[-1] == 99  # the most precise and the farthest
    assert np.all(np.diff(spread) >= 10)  # evenly over the ranks


def test_a_map_fix_beyond_the_predictions_uncertainty_and_the_updates_reach_is_refused():
    """MotionModel.fix_is_plausible: the consensus's pose against the predicted pose. Within the
    update's reach (1 m, 5°) it is fused; beyond it, only within 5σ of a measured increment, or of
    what the vehicle's limits allow since the last frame when nothing measured the motion."""
    import math
    from types import SimpleNamespace

    from robotd.core.geometry import se3, se3_inverse
    from robotd.core.msgs import MotionIncrement
    from robotd.pipeline.stages.motion import MotionModel
    from robotd.pipeline.stages.tracking import PipelineCounters

    cfg = load_config(None, {"vehicle": {"max_speed_mps": 10.0, "max_rate_radps": 2.0}})
    me = SimpleNamespace(cfg=cfg, last_t_ns=0, counters=PipelineCounters())
    view = se3(np.eye(3), np.array([5.0, 1.0, 0.0]))

    def similarity_of(T_world_robot: np.ndarray) -> np.ndarray:
        return se3_inverse(T_world_robot)  # maps world points into the robot frame, s = 1

    def rot_z(deg: float) -> np.ndarray:
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])

    tight = MotionIncrement(0, 100_000_000, np.array([1.0, 0, 0]), np.zeros(3), np.diag([1e-4] * 3 + [1e-6] * 3))
    dt_ns = 100_000_000  # 0.1 s: the limits allow 1 m and 0.2 rad

    def ok(T: np.ndarray, inc: MotionIncrement | None, measured: bool) -> bool:
        return MotionModel.fix_is_plausible(me, similarity_of(T), view, inc, measured, dt_ns)  # type: ignore[arg-type]

    assert MotionModel.fix_is_plausible(me, None, view, tight, True, dt_ns)  # type: ignore[arg-type]
    near = view @ se3(rot_z(3.0), np.array([0.6, 0.3, 0.0]))
    assert ok(near, tight, True)  # within the update's reach
    far = view @ se3(np.eye(3), np.array([17.0, 0.0, 0.0]))
    turned = view @ se3(rot_z(20.0), np.zeros(3))
    assert not ok(far, tight, True) and not ok(turned, tight, True)
    assert me.counters.implausible_fixes == 2
    # nothing measured the motion: what the vehicle's limits allow since the last frame is the
    # prediction's 5σ: over 0.1 s (1 m, 11.5°) 17 m and 20° stay refused; over 0.5 s (5 m, 57°)
    # a 3 m, 20° fix passes
    assert not ok(far, None, False) and not ok(turned, None, False)
    slow = view @ se3(rot_z(20.0), np.array([3.0, 0, 0]))
    assert MotionModel.fix_is_plausible(me, similarity_of(slow), view, None, False, 5 * dt_ns)  # type: ignore[arg-type]
    loose = MotionIncrement(0, 100_000_000, np.array([1.0, 0, 0]), np.zeros(3), np.diag([1.0] * 3 + [0.01] * 3))
    assert ok(view @ se3(rot_z(20.0), np.array([3.0, 0, 0])), loose, True)  # a loose odometry prior allows more


def test_the_deferred_offset_measurement_gives_the_same_run_whoever_runs_it(shared_data) -> None:
    """``Pipeline.after_step`` (the daemon, after queueing the pose) or the next step's ``offset``
    stage (a replay): the same offset, the same poses, bit for bit; only where it is timed moves."""
    root = shared_data("kitti-seq1")
    with drivers.open_camera(f"kitti://{root}") as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(12)]
        rig = cam.rectified_model()
    cfg = load_config(None, {"slam": {"n_particles": 30}})
    a = Pipeline(cfg, rig, np.random.default_rng(1))
    b = Pipeline(cfg, rig, np.random.default_rng(1))
    after_ms = []
    for f in frames:
        ra, rb = a.step(f, None), b.step(f, None)
        after_ms.append(b.after_step())
        np.testing.assert_array_equal(ra.pose.T_world_robot, rb.pose.T_world_robot)
        np.testing.assert_array_equal(ra.pose.cov, rb.pose.cov)  # the offsets each step used: equal
        assert ("offset" in ra.timings_ms) and ("offset" in rb.timings_ms)
    a.after_step()
    assert a.frontend.disparity_bias.value_px == b.frontend.disparity_bias.value_px
    assert b.frontend.disparity_bias.fused >= 2  # the offset was measured (every 2 m of KITTI's 1.2 m frames)
    assert all(ms > 0 for ms in after_ms)  # a pose was pending after every tracked step
    assert b.after_step() == 0.0  # and nothing once it ran
