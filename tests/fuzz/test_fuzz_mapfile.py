"""Saved maps with a valid checksum and mutated content, through the daemon's resume path.

Start from a real map (a pipeline's state after ``sim://`` frames, made once per session), mutate
its content (drop keys, change types, dtypes and shapes, put NaN, inf, huge or negative values in,
truncate arrays, forge packed-array headers), seal it with a valid checksum, resume from it as the
daemon does (``MapFileOutput.resume``) and step the pipeline. The outcome is one of two: a clean
refusal (one log line; the file moved aside under a new name, or, for a valid map of another
configuration, left for ``persistence.keep_maps``), or a working filter that steps, publishes and
saves. Any other exception fails the test. ``ROBOTD_FUZZ_EXAMPLES`` runs more examples.
"""

from __future__ import annotations

import logging
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robotd.outputs.mapfile import MapFileOutput
from tests.support import saved_maps

MAX_EXAMPLES = int(os.environ.get("ROBOTD_FUZZ_EXAMPLES", "60"))
VARIANTS = (("fastslam2", 3), ("ekf", 3), ("fastslam1", 2))

_DROP = object()
ODD_VALUES: tuple[Any, ...] = (
    None,
    "x",
    b"\x00",
    True,
    0,
    -1,
    2**31,
    2**62,
    2**63 - 1,
    2**64,
    -(2**63),
    1.5,
    -0.0,
    float("nan"),
    float("inf"),
    -float("inf"),
    1e300,
    [],
    [1, 2],
    {},
    {"a": 1},
    np.zeros(0),
    np.zeros((2, 2)),
    np.zeros(3, np.int64),
    np.array(["a"]),
)
ODD_ELEMENTS = (float("nan"), float("inf"), -float("inf"), 1e300, -1e300, 1e20, -1.0, 0.0, 2**62, 2**63 - 1, -(2**63))
DTYPES = ("<f8", "<f4", "<i8", "<i4", "|u1", "|b1", "<c16", "<u8")
FORGED_HEADERS: tuple[dict[str, Any], ...] = (
    {"dtype": "f8,(2", "shape": [1], "data": b""},
    {"dtype": "O", "shape": [1], "data": b"\x00" * 8},
    {"dtype": "<f8", "shape": [-1], "data": b"\x00" * 16},
    {"dtype": "<f8", "shape": [2**40, 2**40], "data": b""},
    {"dtype": "(2,3)f8", "shape": [1], "data": b"\x00" * 48},
    {"dtype": "<U2", "shape": [1], "data": b"\x00" * 8},
    {"dtype": "<f8", "shape": [1], "data": "text"},
    {"dtype": "<f8", "shape": None, "data": b""},
    {"dtype": {"names": ["a"], "formats": ["<f8"]}, "shape": [1], "data": b"\x00" * 8},
)


def _paths(tree: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    out: list[tuple[str, ...]] = []
    for k, v in tree.items():
        if isinstance(v, dict):
            out += [(*prefix, k), *_paths(v, (*prefix, k))]
        else:  # values are mutated more often than whole tables are dropped
            out += [(*prefix, k)] * 3
    return out


PATHS: dict[tuple[str, int], list[tuple[str, ...]]] = {}  # filled on first use (the map is made then)


def _all_paths(variant: tuple[str, int]) -> list[tuple[str, ...]]:
    if variant not in PATHS:
        PATHS[variant] = _paths(saved_maps.saved_state(*variant))
    return PATHS[variant]


def _mutate_array(a: np.ndarray, op: str, k: int, data: st.DataObject) -> Any:
    """One mutation of an array; ``k`` picks the element or axis. The first kinds keep the map
    structurally valid (so that the filter runs on odd but plausible content), the others break it."""
    if a.dtype.kind not in "biufc":  # an array an earlier mutation put in (strings): replaced whole
        return data.draw(st.sampled_from(ODD_VALUES))
    if op == "scale" and a.size:  # every value scaled: a map from far away, covariances inflated, ...
        with np.errstate(all="ignore"):
            return a * np.asarray(data.draw(st.sampled_from(SCALES))).astype(a.dtype)
    if op == "element" and a.size:  # one value changed by a factor, or odd
        b = a.copy()
        flat = b.reshape(-1)
        with np.errstate(all="ignore"):
            value = data.draw(st.sampled_from((*(flat[k % a.size] * f for f in SCALES), *ODD_ELEMENTS)))
            try:
                flat[k % a.size] = value
            except (OverflowError, ValueError, TypeError):
                flat[k % a.size] = np.iinfo(a.dtype).max if a.dtype.kind in "iu" else np.nan
        return b
    if op == "shuffle" and a.ndim:  # rows reordered (particles, landmarks, ids)
        return a[np.random.default_rng(k).permutation(a.shape[0])]
    if op == "truncate" and a.ndim:  # shortened (or emptied) along one axis
        axis = k % a.ndim
        return np.take(a, np.arange(a.shape[axis] // (2 + k % 3)), axis=axis)
    if op == "dtype":
        return a.astype(data.draw(st.sampled_from(DTYPES)))
    if op == "reshape":
        return a.reshape((1, *a.shape)) if k % 2 else a.reshape(-1)
    if op == "swap" and a.ndim >= 2:
        return np.swapaxes(a, 0, 1).copy()
    if op == "forge":
        return {"__nd__": data.draw(st.sampled_from(FORGED_HEADERS))}
    return a


SCALES = (-1.0, 0.0, 1e-300, 1e-3, 2.0, 10.0, 1e3, 1e7)
# the first six keep the structure (so that many mutated maps load and the filter runs on them)
ARRAY_OPS: tuple[str, ...] = ("scale", "scale", "element", "element", "element", "shuffle")
ARRAY_OPS += ("truncate", "dtype", "reshape", "swap", "forge")


def _mutate(state: dict[str, Any], variant: tuple[str, int], data: st.DataObject) -> None:
    path = data.draw(st.sampled_from(_all_paths(variant)))
    parent: Any = state
    for key in path[:-1]:
        parent = parent.get(key) if isinstance(parent, dict) else None
        if not isinstance(parent, dict):
            return  # an earlier mutation removed or replaced the table
    key = path[-1]
    if key not in parent:
        return
    kind = data.draw(st.sampled_from(("drop", "replace", "tweak", "tweak", "tweak", "tweak")))
    old = parent[key]
    if kind == "drop":
        del parent[key]
    elif kind == "replace" or isinstance(old, dict | str | bool):
        parent[key] = data.draw(st.sampled_from(ODD_VALUES))
    elif isinstance(old, np.ndarray):
        op = data.draw(st.sampled_from(ARRAY_OPS))
        parent[key] = _mutate_array(old, op, data.draw(st.integers(0, 2**31)), data)
    elif isinstance(old, int):
        parent[key] = data.draw(st.sampled_from((old + 1, old - 1, -old - 1, 0, 2**62, 2**63 - 1, 2**64, float(old))))
    elif isinstance(old, float):
        as_int = int(old) if math.isfinite(old) else 0
        parent[key] = data.draw(
            st.sampled_from((-old, old / 2, old * 1e6, 0.0, 1e-300, float("nan"), float("inf"), 1e308, as_int))
        )


class _Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def _resume_and_run(blob: bytes, variant: tuple[str, int]) -> None:
    frames, _ = saved_maps.sim_frames()
    log = _Lines()
    logger = logging.getLogger("robotd")
    level = logger.level
    logger.addHandler(log)
    logger.setLevel(logging.INFO)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            state_dir = Path(tmp)
            (state_dir / "map.robotd").write_bytes(blob)
            pipeline = saved_maps.pipeline(*variant)
            out = MapFileOutput(saved_maps.config(*variant, state_dir=state_dir).persistence, "r1")
            try:
                resumed = out.resume(pipeline)
                if not resumed:
                    failed = [line for line in log.lines if line.startswith("resume failed")]
                    assert len(failed) == 1 and "\n" not in failed[0], log.lines
                    aside = list(state_dir.glob("map.robotd.bad-*"))
                    if "moved aside to" in failed[0]:
                        assert [a.read_bytes() for a in aside] == [blob] and not (state_dir / "map.robotd").exists()
                    else:  # a valid map of another configuration: left for keep_maps, untouched
                        assert not aside and (state_dir / "map.robotd").read_bytes() == blob, failed[0]
                    assert pipeline.estimator.landmark_ids().size == 0  # nothing reached the filter
                # a working filter: steps as the daemon does (relocalising first), then with the
                # filter predicting and updating, publishes its map and saves it
                pipeline.step(frames[saved_maps.N_MAP_FRAMES], None)
                pipeline.relocaliser.arm(0)
                for f in frames[saved_maps.N_MAP_FRAMES + 1 : saved_maps.N_MAP_FRAMES + 3]:
                    pipeline.step(f, None)
                pipeline.estimator.landmarks()
                assert out.save(pipeline.state_dict(), 2)
            finally:
                out.close()
    finally:
        logger.removeHandler(log)
        logger.setLevel(level)


@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(variant=st.sampled_from(VARIANTS), n=st.integers(1, 3), data=st.data())
def test_a_mutated_map_is_refused_cleanly_or_runs(variant: tuple[str, int], n: int, data: st.DataObject) -> None:
    state = saved_maps.saved_state(*variant)
    for _ in range(n):
        _mutate(state, variant, data)
    _resume_and_run(saved_maps.seal(state), variant)


@settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(variant=st.sampled_from(VARIANTS), n=st.integers(1, 3), data=st.data())
def test_a_map_with_odd_values_is_refused_cleanly_or_runs(
    variant: tuple[str, int], n: int, data: st.DataObject
) -> None:
    # the structure kept, the values changed: most of these maps load, and the filter must run
    state = saved_maps.saved_state(*variant)
    arrays = [p for p in _all_paths(variant) if isinstance(_get(state, p), np.ndarray)]
    for _ in range(n):
        path = data.draw(st.sampled_from(arrays))
        op = data.draw(st.sampled_from(("scale", "element", "element", "shuffle")))
        parent = _get(state, path[:-1])
        parent[path[-1]] = _mutate_array(parent[path[-1]], op, data.draw(st.integers(0, 2**31)), data)
    _resume_and_run(saved_maps.seal(state), variant)


def _get(tree: dict[str, Any], path: tuple[str, ...]) -> Any:
    for key in path:
        tree = tree[key]
    return tree


def test_the_unmutated_map_resumes() -> None:
    # the property's baseline: without a mutation every variant loads and runs
    for variant in VARIANTS:
        log = _Lines()
        logging.getLogger("robotd").addHandler(log)
        try:
            _resume_and_run(saved_maps.seal(saved_maps.saved_state(*variant)), variant)
        finally:
            logging.getLogger("robotd").removeHandler(log)
        assert any(line.startswith("resumed from saved map") for line in log.lines), (variant, log.lines)
