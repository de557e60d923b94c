"""Odometry integration: velocity samples -> the motion increment between two frame times.

Samples (robotd.msgs.Odometry) are body-frame velocities and rates on the host monotonic clock.
Between two capture times the body motion is integrated with a zero-order hold of each sample
(the latest sample at or before a time holds until the next one), composing rotations exactly
(SO(3) exponential), so the increment is expressed in the robot frame at the earlier frame.
"""

from __future__ import annotations

from collections import deque

import numpy as np

from robotd.geometry import so3_exp, so3_log
from robotd.msgs import MotionIncrement, Odometry


class OdometryIntegrator:
    """Keeps recent samples and integrates them between frame times."""

    def __init__(self, max_samples: int = 4096, max_gap_s: float = 0.5) -> None:
        self._t: deque[int] = deque(maxlen=max_samples)
        self._v: deque[np.ndarray] = deque(maxlen=max_samples)
        self._w: deque[np.ndarray] = deque(maxlen=max_samples)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.out_of_order = 0
        self.gaps = 0

    def add(self, odo: Odometry) -> None:
        if self._t and odo.t_ns < self._t[-1]:
            self.out_of_order += 1  # a late sample cannot rewrite the past; drop it
            return
        self._t.append(int(odo.t_ns))
        self._v.append(np.asarray(odo.vel_R_mps, float))
        self._w.append(np.asarray(odo.rate_R_radps, float))

    @property
    def latest_t_ns(self) -> int | None:
        return self._t[-1] if self._t else None

    def integrate(self, t0_ns: int, t1_ns: int) -> MotionIncrement | None:
        """The increment from t0 to t1, or None when the samples do not cover the interval."""
        if t1_ns < t0_ns or not self._t:
            return None
        t = np.fromiter(self._t, np.int64)
        # coverage: a sample at or before t0 (within max_gap) and data reaching close to t1
        i0 = int(np.searchsorted(t, t0_ns, side="right")) - 1
        if i0 < 0 or t0_ns - t[i0] > self.max_gap_ns or t1_ns - t[-1] > self.max_gap_ns:
            self.gaps += 1
            return None
        V = np.asarray(self._v)
        W = np.asarray(self._w)
        # segment boundaries: t0, sample times inside (t0, t1), t1
        inner = np.nonzero((t > t0_ns) & (t < t1_ns))[0]
        bounds = np.concatenate([[t0_ns], t[inner], [t1_ns]])
        seg_idx = np.concatenate([[i0], inner])
        if np.any(np.diff(t[max(i0, 0) :]) > self.max_gap_ns):
            # a hole inside the interval: holding one sample across it would invent motion
            within = t[max(i0, 0) :]
            holes = np.diff(within) > self.max_gap_ns
            if np.any(holes & (within[1:] > t0_ns) & (within[:-1] < t1_ns)):
                self.gaps += 1
                return None
        R = np.eye(3)
        p = np.zeros(3)
        for k in range(len(seg_idx)):
            dt = (bounds[k + 1] - bounds[k]) * 1e-9
            if dt <= 0:
                continue
            j = seg_idx[k]
            # translation along the segment with the rotation at its midpoint (second order)
            R_mid = R @ so3_exp(W[j] * dt / 2.0)
            p = p + R_mid @ (V[j] * dt)
            R = R @ so3_exp(W[j] * dt)
        return MotionIncrement(int(t0_ns), int(t1_ns), p, so3_log(R), np.zeros((6, 6)))

    def prune_before(self, t_ns: int) -> None:
        """Forget samples no longer needed (keep the last one at or before t_ns)."""
        while len(self._t) >= 2 and self._t[1] <= t_ns:
            self._t.popleft()
            self._v.popleft()
            self._w.popleft()
