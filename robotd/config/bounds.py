"""Bounds on the configuration values that size memory or time, derived from this machine and the
frame deadline (docs/reliability.md, "Configuration bounds").

A value past its bound is refused when the configuration is loaded, in one line naming the key,
the value, the bound and why. The bounds:

- ``slam.n_particles`` (a filter with particles: FastSLAM), the smallest of
  - the fixed ceiling ``MAX_PARTICLES``;
  - memory: half the memory available at start over the worst-case map per particle, every
    particle holding its own copy of ``REFERENCE_LANDMARKS`` landmarks of the size the filter
    declares (FastSLAM 3-D: mean and covariance, 12 float64 = 96 B; 2-D: 6 float64 = 48 B;
    bench/fastslam.py measured the copy-on-write store at this size, docs/benchmarks.md);
  - time: the filter alone must fit the deadline at full settings. The filter declares its step's
    cost per particle and observation on the reference machine (FastSLAM: bench/fastslam.py,
    1000 particles × 100 observations, one core), and a frame carries at most
    ``slam.max_updates_per_frame + slam.max_new_per_frame`` observations (no more than
    ``frontend.max_features``). The deadline is ``budget.deadline_ms``, or the frame period at
    ``DEFAULT_FRAME_RATE_HZ`` when it is 0 (the camera's rate is not known before it is opened).
- ``frontend.max_features``: memory. The frame-to-frame descriptor match builds a (N, N) float32
  distance matrix, about ``FEATURE_MATCH_BYTES`` per pair at its peak (the matrix and numpy's
  temporaries); at most half the available memory. Time is the latency budget's to manage: it
  halves the features first, and a detector's cost per feature differs tenfold (ORB against SIFT).

The filter's costs are those it declared at its registration (robotd.slam.factory.ParticleCost).
"""

from __future__ import annotations

import functools
import math
import os
from dataclasses import dataclass

from robotd.core.choices import MAX_PARTICLES
from robotd.core.errors import ConfigError, show_value
from robotd.slam.factory import ParticleCost, estimator_kind

MEMORY_SHARE = 0.5  # of the memory available at start, for one of these consumers
REFERENCE_LANDMARKS = 10_000  # map size of the memory bound (the largest bench/fastslam.py measured)
DEFAULT_FRAME_RATE_HZ = 30.0
FEATURE_MATCH_BYTES = 16  # per (feature, feature) pair: four (N, N) float32 arrays at the peak


@functools.cache
def available_memory_bytes() -> int:
    """Memory available to a new process: MemAvailable from /proc/meminfo, else the physical
    memory (read once per process, so a configuration accepted once stays accepted)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (OSError, ValueError, AttributeError):
        return 1 << 30  # unknown: assume the smallest board robotd runs on (1 GB)


@dataclass(frozen=True)
class Sizing:
    """The configuration values the bounds read (robotd.config builds it; this module does not
    import the config, which imports it)."""

    filter: str  # slam.filter
    dim: int  # slam.dim
    n_particles: int  # slam.n_particles
    max_updates_per_frame: int  # slam.max_updates_per_frame
    max_new_per_frame: int  # slam.max_new_per_frame
    max_features: int  # frontend.max_features
    deadline_ms: float  # budget.deadline_ms (0: one frame period)


def deadline_ms(cfg: Sizing) -> float:
    return cfg.deadline_ms or 1000.0 / DEFAULT_FRAME_RATE_HZ


def particle_bound(cfg: Sizing, cost: ParticleCost) -> tuple[int, str]:
    """The largest ``slam.n_particles`` for this configuration on this machine, for a filter whose
    particles cost ``cost``, and why."""
    mem = available_memory_bytes()
    per_particle = cost.landmark_bytes[cfg.dim] * REFERENCE_LANDMARKS
    by_memory = int(MEMORY_SHARE * mem // per_particle)
    obs = min(cfg.max_updates_per_frame + cfg.max_new_per_frame, cfg.max_features)
    us = cost.step_us_per_obs
    by_time = int(min(deadline_ms(cfg) * 1000.0 / (us * max(obs, 1)), float(MAX_PARTICLES)))
    bound = min(MAX_PARTICLES, by_memory, by_time)
    if bound == MAX_PARTICLES:
        why = "the fixed ceiling"
    elif bound == by_memory:
        why = (
            f"{MEMORY_SHARE:.0%} of the memory available for {REFERENCE_LANDMARKS} landmarks of "
            f"{per_particle / 1e6:.2f} MB per particle"
        )
    else:
        why = (
            f"{us} µs per particle and observation, {obs} observations a frame "
            "(slam.max_updates_per_frame + max_new_per_frame), must fit the deadline; "
            "raise budget.deadline_ms for offline runs"
        )
    return bound, why


def feature_bound(cfg: Sizing) -> int:
    """The largest ``frontend.max_features`` this machine's memory allows."""
    return math.isqrt(int(MEMORY_SHARE * available_memory_bytes() // FEATURE_MATCH_BYTES))


def check_bounds(cfg: Sizing) -> None:
    """ConfigError, one line naming the key, its value, the bound and why, for a value past its bound."""
    here = f"on this machine ({available_memory_bytes() / 1e9:.1f} GB available, {deadline_ms(cfg):.1f} ms deadline)"
    cost = estimator_kind(cfg.filter).particles  # ConfigError for an unregistered filter
    if cost is not None:
        bound, why = particle_bound(cfg, cost)
        if cfg.n_particles > bound:
            raise ConfigError(f"slam.n_particles = {show_value(cfg.n_particles)}: at most {bound} {here}: {why}")
    fb = feature_bound(cfg)
    if cfg.max_features > fb:
        raise ConfigError(
            f"frontend.max_features = {show_value(cfg.max_features)}: at most {fb} {here}: the frame-to-frame "
            f"match holds {FEATURE_MATCH_BYTES} B per pair of features in {MEMORY_SHARE:.0%} of the memory available"
        )
