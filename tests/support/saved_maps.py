"""Real saved maps for the persistence tests: the state of a pipeline that ran on ``sim://`` frames,
made once per test session, and the map file format written around any (mutated) content.

``seal`` writes the documented file layout (robotd.formats.persist: magic, length, CBOR payload, CRC-32)
itself, so a test can put content into a file that ``MapStore.save`` would never write, with a
checksum that holds.
"""

from __future__ import annotations

import copy
import functools
import struct
import zlib
from pathlib import Path
from typing import Any

import cbor2
import numpy as np

import drivers
from robotd.config import Config, load_config
from robotd.core.msgs import StereoFrame
from robotd.core.stereo import RectifiedStereo
from robotd.formats.codec import pack_tree
from robotd.formats.persist import MAGIC, STATE_SCHEMA
from robotd.pipeline.step import Pipeline

N_MAP_FRAMES = 20  # frames the saved map is built from (~100 landmarks)
# small, so that each fuzz example (EKF SLAM's cost grows with the square of the map) is cheap
N_PARTICLES = 20
MAX_NEW_PER_FRAME = 8
MAX_UPDATES_PER_FRAME = 20


@functools.cache
def sim_frames() -> tuple[tuple[StereoFrame, ...], RectifiedStereo]:
    """The first frames of the simulated yard (and its rig): the map is built from the first
    ``N_MAP_FRAMES``, later frames step a resumed pipeline."""
    with drivers.open_camera("sim://?realtime=0&fps=30&seed=2") as cam:
        it = cam.frames()
        frames = tuple(next(it) for _ in range(N_MAP_FRAMES + 4))
        rig = cam.rectified_model()
    return frames, rig


def config(filt: str = "fastslam2", dim: int = 3, state_dir: str | Path = "", **frontend: Any) -> Config:
    return load_config(
        None,
        {
            "slam": {
                "filter": filt,
                "dim": dim,
                "n_particles": N_PARTICLES,
                "max_new_per_frame": MAX_NEW_PER_FRAME,
                "max_updates_per_frame": MAX_UPDATES_PER_FRAME,
            },
            "frontend": frontend,
            "persistence": {"state_dir": str(state_dir), "save_period_s": 0.0, "resume": True},
        },
    )


def pipeline(filt: str = "fastslam2", dim: int = 3, **frontend: Any) -> Pipeline:
    """A fresh pipeline of that filter on the sim rig (what a resuming daemon starts with)."""
    _, rig = sim_frames()
    return Pipeline(config(filt, dim, **frontend), rig, np.random.default_rng(7))


@functools.cache
def _state(filt: str, dim: int) -> dict[str, Any]:
    frames, _ = sim_frames()
    p = pipeline(filt, dim)
    for f in frames[:N_MAP_FRAMES]:
        p.step(f, None)
    return p.state_dict()


def saved_state(filt: str = "fastslam2", dim: int = 3) -> dict[str, Any]:
    """A copy (the caller may mutate it) of the state a pipeline of that filter saves."""
    return copy.deepcopy(_state(filt, dim))


def payload(state: Any, robot: str = "r1", t_ns: int = 1, **top: Any) -> bytes:
    """The CBOR payload of a map file holding ``state`` (arrays packed as robotd.formats.codec does);
    ``top`` replaces or adds top-level payload keys."""
    msg = {"schema": STATE_SCHEMA, "robot": robot, "saved_unix_s": 0.0, "t_ns": t_ns, "state": pack_tree(state)}
    msg.update(top)
    return cbor2.dumps(msg)


def seal_payload(data: bytes) -> bytes:
    """A map file around any payload bytes (CBOR or not), its length and checksum valid."""
    return MAGIC + struct.pack("<Q", len(data)) + data + struct.pack("<I", zlib.crc32(data))


def seal(state: Any, robot: str = "r1", t_ns: int = 1, **top: Any) -> bytes:
    """A map file holding ``state`` with a valid checksum (``payload`` for the arguments)."""
    return seal_payload(payload(state, robot, t_ns, **top))
