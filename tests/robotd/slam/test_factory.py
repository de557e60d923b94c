"""An estimator declares what it is at its registration (robotd.slam.factory), and nothing outside
the factory asks for it by name.

A fake estimator (``DeadReckoning``, below: the ``Estimator`` protocol and nothing else) is added by
registering it, and only that, and runs through every path that used to compare ``slam.filter``
with ``"ekf"``: the configuration and its particle bounds, the pipeline and its reported
covariance, the daemon's latency budget and its map file.
"""

from __future__ import annotations

import ast
import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

import drivers
from robotd.config import bounds as config_bounds
from robotd.config import config_from_dict, load_config
from robotd.config.bounds import Sizing, check_bounds
from robotd.core.errors import ConfigError, PersistenceError
from robotd.core.geometry import R_to_euler, pose6_to_T, se3, so3_exp, transform_points
from robotd.core.msgs import LandmarkMap, MotionIncrement, Observations, PoseEstimate, UpdateReport
from robotd.daemon import Daemon
from robotd.pipeline.step import Pipeline
from robotd.slam import factory
from robotd.slam.estimator import Estimator, Persistent, persistent
from robotd.slam.factory import ESTIMATORS, EstimatorKind, ParticleCost, make_estimator, register, unregister
from robotd.slam.params import SlamParams
from tests.support.daemon_runs import HANG_GUARD_S, run_until
from tests.support.paths import REPO

GB = 1 << 30
FAKE = "dead_reckoning"


class DeadReckoning:
    """Integrates the motion and keeps each landmark where it was first seen: no correction, no
    particles, no persistence."""

    name = FAKE

    def __init__(self, params: SlamParams) -> None:
        self.dim = params.dim
        self.T = np.eye(4)
        self.t_ns = 0
        self.points: dict[int, np.ndarray] = {}

    def predict(self, inc: MotionIncrement) -> None:
        self.T = self.T @ se3(so3_exp(inc.drot_R_rad), inc.dp_R_m)
        self.t_ns = inc.t1_ns

    def update(self, obs: Observations) -> UpdateReport:
        new = obs.is_new
        self.points.update(zip(obs.ids[new].tolist(), transform_points(self.T, obs.xyz_R_m[new])))
        self.t_ns = obs.t_ns
        return UpdateReport(n_new=int(new.sum()))

    def update_gravity(self, g_R, g_W, sigma_rad, reopen=False) -> tuple[bool, float]:
        return False, 0.0

    def estimate(self) -> PoseEstimate:
        return PoseEstimate(self.t_ns, self.T[:3, 3].copy(), R_to_euler(self.T[:3, :3]), 1e-4 * np.eye(6))

    def landmarks(self) -> LandmarkMap:
        ids = self.landmark_ids()
        xyz = np.array([self.points[i] for i in ids.tolist()]).reshape(-1, 3)
        return LandmarkMap(ids, xyz, np.tile(1e-2 * np.eye(3), (ids.size, 1, 1)))

    def landmark_ids(self) -> np.ndarray:
        return np.fromiter(self.points, np.int64, len(self.points))

    def set_particles(self, n: int) -> int:
        return 1

    def reset_pose(self, x: np.ndarray, cov: np.ndarray | None = None) -> None:
        self.T = pose6_to_T(x)

    def hold_landmarks(self, below_id: int) -> None:
        pass

    def spread_kept(self) -> float:
        return 0.0


NO_PARTICLES = EstimatorKind(particles=None, anchored_covariance=False)
# a particle filter of the fake's own costs: 2 µs per particle and observation, 1 kB per landmark
COSTLY = EstimatorKind(ParticleCost(2.0, {2: 1000, 3: 1000}), anchored_covariance=True)


@pytest.fixture
def fake() -> Iterator[Callable[[EstimatorKind], None]]:
    """Register ``DeadReckoning`` as ``slam.filter = "dead_reckoning"`` with the kind given."""

    def add(kind: EstimatorKind) -> None:
        register(FAKE, kind, lambda params, rng, visible: DeadReckoning(params))

    yield add
    if FAKE in ESTIMATORS:
        unregister(FAKE)


@pytest.fixture(scope="module")
def sim_frames():
    with drivers.open_camera("sim://?realtime=0&fps=30&seed=2") as cam:
        it = cam.frames()
        frames = [next(it) for _ in range(12)]
        rig = cam.rectified_model()
    return frames, rig


def test_the_fake_satisfies_the_estimator_protocol_and_not_the_persistence_one() -> None:
    est = DeadReckoning(SlamParams())
    assert isinstance(est, Estimator) and not isinstance(est, Persistent)
    with pytest.raises(PersistenceError, match="'dead_reckoning' filter cannot be saved"):
        persistent(est)
    for name in ("ekf", "fastslam1", "fastslam2"):
        built = make_estimator(SlamParams(filter=name, dim=2, n_particles=2))
        assert isinstance(built, Estimator) and persistent(built) is built and built.name == name


def test_the_configuration_offers_a_registered_estimator_and_bounds_it_by_its_declared_costs(
    fake, monkeypatch: pytest.MonkeyPatch
) -> None:
    with pytest.raises(ConfigError, match=r"slam.filter: expected one of \['ekf', 'fastslam1', 'fastslam2'\]"):
        config_from_dict({"slam": {"filter": FAKE}})
    fake(COSTLY)
    monkeypatch.setattr(config_bounds, "available_memory_bytes", lambda: 64 * GB)
    # time: 33.3 ms at 2 µs per particle and observation, 80 + 40 observations a frame: 138 particles
    assert config_from_dict({"slam": {"filter": FAKE, "n_particles": 138}}).slam.filter == FAKE
    with pytest.raises(ConfigError, match=r"n_particles = 139: at most 138 .* 2.0 µs per particle and observation"):
        config_from_dict({"slam": {"filter": FAKE, "n_particles": 139}})
    # memory: half of 1 GiB over 10 000 landmarks × 1 kB per particle: 53 particles
    monkeypatch.setattr(config_bounds, "available_memory_bytes", lambda: 1 * GB)
    slow = {"budget": {"deadline_ms": 1000.0}}
    assert config_from_dict({**slow, "slam": {"filter": FAKE, "n_particles": 53}}).slam.n_particles == 53
    with pytest.raises(ConfigError, match=r"n_particles = 54: at most 53 .* 10.00 MB per particle"):
        config_from_dict({**slow, "slam": {"filter": FAKE, "n_particles": 54}})


def test_a_registered_estimator_without_particles_has_no_particle_bound(fake) -> None:
    fake(NO_PARTICLES)
    assert config_from_dict({"slam": {"filter": FAKE, "n_particles": 100000}}).slam.n_particles == 100000


def test_an_unregistered_name_is_a_clear_error_not_a_key_error() -> None:
    sizing = Sizing("ukf", 3, 100, 80, 40, 2000, 0.0)
    with pytest.raises(ConfigError, match=r"slam.filter: 'ukf' is not a registered estimator .*ekf \| fastslam1"):
        check_bounds(sizing)
    with pytest.raises(ConfigError, match="'ukf' is not a registered estimator"):
        make_estimator(SlamParams(filter="ukf"))
    with pytest.raises(ValueError, match="registered already"):
        register("ekf", NO_PARTICLES, lambda params, rng, visible: DeadReckoning(params))


@pytest.mark.parametrize("kind", [NO_PARTICLES, COSTLY], ids=["no-particles", "particles"])
def test_the_pipeline_builds_and_steps_a_registered_estimator(fake, sim_frames, kind: EstimatorKind) -> None:
    """The reported covariance anchors landmarks when the filter declares it; the step needs nothing
    beyond the Estimator protocol; saving needs the Persistent one."""
    fake(kind)
    frames, rig = sim_frames
    cfg = load_config(None, {"slam": {"filter": FAKE, "n_particles": 20}})
    p = Pipeline(cfg, rig, np.random.default_rng(5))
    assert isinstance(p.estimator, DeadReckoning) and p.kind is kind
    assert (p.covariance.anchors is not None) == kind.anchored_covariance
    for f in frames:
        r = p.step(f, None)
    assert p.frontend.descriptors is not None
    np.testing.assert_array_equal(np.sort(p.frontend.descriptors.ids), np.sort(p.estimator.landmark_ids()))
    assert r.report.n_new >= 0 and np.linalg.norm(r.pose.xyz_W_m) > 0.05  # it moved with the visual motion
    with pytest.raises(PersistenceError, match="cannot be saved"):
        p.state_dict()


@pytest.mark.parametrize("kind", [NO_PARTICLES, COSTLY], ids=["no-particles", "particles"])
def test_the_daemon_runs_a_registered_estimator_by_what_it_declares(
    fake, tmp_path: Path, caplog: pytest.LogCaptureFixture, kind: EstimatorKind
) -> None:
    """The latency budget trades particles only for a filter that has them; a filter that is not
    Persistent runs without a map file (none is written or read)."""
    fake(kind)
    cfg = load_config(
        None,
        {
            "camera": {"url": "sim://?fps=20"},
            "vehicle": {"url": "sim://?fps=20"},
            "zenoh": {"enabled": False},
            "persistence": {"state_dir": str(tmp_path), "save_period_s": 0.5},
            "slam": {"filter": FAKE, "n_particles": 40},
        },
    )
    d = Daemon(cfg, duration_s=HANG_GUARD_S, environ={})
    with caplog.at_level(logging.INFO, logger="robotd"):
        status, reached = run_until(d, lambda: d.stats.published >= 8)
    assert status == 0 and reached and not d.failed, (d.stop_reason, d.failed)
    assert d.budget is not None and d.budget.state.n_particles == (40 if kind.particles else 1)
    assert "map file: none (the 'dead_reckoning' filter cannot be saved or resumed)" in caplog.text
    assert d.maps is None and not (tmp_path / "map.robotd").exists()


# --------------------------------------------------------------------------------------------
# nothing outside the factory compares against an estimator's name

SCANNED = ("robotd", "drivers", "bench")
# studies that select rows of their own results by the filter that produced them (names as
# inputs, not a decision about a filter): (file, the comparison)
STUDY_ROWS = {
    ("robotd/research/experiments.py", "r.filter == 'fastslam1'"),
    ("robotd/research/experiments.py", "r.filter == 'fastslam2'"),
    ("bench/fastslam.py", "r['filter'] == 'fastslam2'"),
}


def _name_comparisons(source: str, names: set[str]) -> list[tuple[int, str]]:
    """(line, comparison) of each ``==``/``!=``/``in`` with a name in ``names`` (alone or in a
    tuple, list or set), and each ``match`` case on one."""
    hits: list[tuple[int, str]] = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
        elif isinstance(node, ast.MatchValue):
            sides = [node.value]
        else:
            continue
        for side in sides:
            elts = side.elts if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [side]
            if any(isinstance(e, ast.Constant) and e.value in names for e in elts):
                hits.append((node.lineno, ast.unparse(node)))
                break
    return hits


def test_the_scan_finds_a_name_comparison() -> None:
    names = {"ekf", "fastslam2"}
    src = (
        'a = cfg.slam.filter != "ekf"\n'
        'b = f in ("fastslam2", "x")\n'
        'c = f == "ukf"\n'
        "match f:\n"
        '    case "ekf":\n'
        "        pass\n"
    )
    assert [line for line, _ in _name_comparisons(src, names)] == [1, 2, 5]


def test_no_module_outside_the_factory_compares_against_an_estimator_name() -> None:
    names = set(ESTIMATORS)
    factory_file = Path(factory.__file__).resolve()
    bad: list[str] = []
    for pkg in SCANNED:
        for f in sorted((REPO / pkg).rglob("*.py")):
            if f.resolve() == factory_file:
                continue
            rel = f.relative_to(REPO).as_posix()
            for line, text in _name_comparisons(f.read_text(encoding="utf-8"), names):
                if (rel, text) not in STUDY_ROWS:
                    bad.append(f"{rel}:{line}: {text}")
    assert not bad, "decide by the declared EstimatorKind (robotd.slam.factory), not the name:\n" + "\n".join(bad)
