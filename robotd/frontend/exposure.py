"""The cameras' exposure estimated from the images' own motion, for sources that report none.

The measurements' blur model (robotd.core.stereo.blur_covariance, docs/math.md §3.4) needs the
exposure: the streak a turn draws is b = rate × exposure × f. The OAK-D reports it with every
frame; a dataset folder does not. What the images do show is how far the corners found
in two frames disagree under the motion the PnP fitted to them: with no blur the residuals are the
detector's noise, and a streak adds b²/12 of variance along it in each of the two frames
(docs/frontend.md "An exposure from the residuals"). Over frames turning at different rates,

    y_k = c + e² · x_k,    x_k = f² (|ω_k|² + |ω_{k−1}|²) / 12,

where y_k is the robust spread (total variance, px²) of frame k's matches' left-image residuals,
ω_k the rotation rate of its motion and ω_{k−1} the previous one's, c the spread with no blur and
e the exposure. :class:`ExposureEstimate` fits (c, e²) by least squares, each pair weighted by
the inverse square of its expected spread (a median's error grows with what it measures), with
exponential forgetting (an auto-exposure camera changes its exposure with the light), and states
e only when the data fix it: at least ``MIN_FAST`` recent frames turned fast enough to streak by ``FAST_STREAK_PX`` at
an exposure of the whole frame interval, and the slope is positive by two of its standard errors.
A still camera or a car on a straight road never gets there, so the estimate is 0 (no blur
modelled) and nothing changes for it. Anything else that spreads the residuals more the faster the
camera turns reads as exposure too (docs/frontend.md says how much on the simulator's rover).
"""

from __future__ import annotations

import math

import numpy as np

from robotd.core.msgs import MotionIncrement

# frames that count as turning fast: the streak they would draw at an exposure of the whole frame
# interval, px (below it a streak hides in the detector's noise at any exposure)
FAST_STREAK_PX = 2.0
# fast frames (forgotten alike) before an estimate is stated
MIN_FAST = 10.0
# how much one frame's evidence weighs against the past (a time constant of 200 frames)
FORGET = 0.995
# the lower bound the slope must clear, in standard errors
SIGNIFICANCE = 2.0


def residual_spread(res: np.ndarray) -> float | None:
    """The robust total variance [px²] of left-image residuals ``res`` (N, 3) over (x_L, x_R, y):
    the median of x_L² + y² over ln 2 (exact for an isotropic Gaussian; the median leaves the
    moving points and false matches out). None with fewer than 8 finite rows."""
    r2 = res[:, 0] ** 2 + res[:, 2] ** 2
    r2 = r2[np.isfinite(r2)]
    if r2.size < 8:
        return None
    return float(np.median(r2)) / math.log(2.0)


class ExposureEstimate:
    """The effective exposure [s] from the frame-to-frame residuals' spread against the turn rate
    (module docstring). :meth:`add` one PnP motion at a time; :meth:`exposure_s` is 0 until the
    data fix it."""

    def __init__(self) -> None:
        self._s = np.zeros(6)  # forgotten weighted sums: w, wx, wy, wx², wxy, wy²
        self._n = 0.0  # forgotten count of pairs
        self._fast = 0.0  # forgotten count of fast pairs
        self._line: tuple[float, float] | None = None  # the last fit (c, e²): the next pair's weight
        self._prev: tuple[int, float] | None = None  # the last motion's end time and rate²
        self._e = 0.0
        self.frames = 0

    def add(self, inc: MotionIncrement, f_px: float, spread_px2: float) -> None:
        """One motion ``inc`` measured by the PnP whose matches' residuals spread ``spread_px2``
        (:func:`residual_spread`) at focal length ``f_px``. A motion that does not follow the last
        one (a gap, a frame without PnP) only starts a new pair; non-finite input is skipped."""
        dt = (inc.t1_ns - inc.t0_ns) * 1e-9
        w2 = float(np.dot(inc.drot_R_rad, inc.drot_R_rad)) / dt**2 if dt > 0.0 else math.nan
        ok = math.isfinite(w2) and math.isfinite(spread_px2) and spread_px2 > 0.0 and f_px > 0.0
        prev, self._prev = self._prev, ((inc.t1_ns, w2) if ok else None)
        if not ok or prev is None or prev[0] != inc.t0_ns:
            return
        x = f_px**2 * (w2 + prev[1]) / 12.0
        y = spread_px2
        # the spread's error grows with the spread (a median over a fixed number of matches): each
        # pair weighs 1 / (its expected spread)², from the last fit (the first pair's own at first)
        c, e2 = self._line if self._line is not None else (y, 0.0)
        w = 1.0 / max(c + e2 * x, 1e-6) ** 2
        self._s = FORGET * self._s + w * np.array([1.0, x, y, x * x, x * y, y * y])
        self._n = FORGET * self._n + 1.0
        self._fast = FORGET * self._fast + float(math.sqrt(w2) * dt * f_px >= FAST_STREAK_PX)
        self.frames += 1
        self._e = self._solve(dt)

    def _solve(self, dt: float) -> float:
        sw, sx, sy, sxx, sxy, syy = self._s
        cxx, cxy, cyy = sxx - sx * sx / sw, sxy - sx * sy / sw, syy - sy * sy / sw
        if cxx <= 0.0 or self._n < 3.0:
            return 0.0
        slope = cxy / cxx
        self._line = ((sy - slope * sx) / sw, max(slope, 0.0))
        if self._fast < MIN_FAST:
            return 0.0
        se = math.sqrt(max(cyy - cxy * cxy / cxx, 0.0) / (self._n - 2.0) / cxx)
        if slope - SIGNIFICANCE * se <= 0.0:
            return 0.0
        return min(math.sqrt(slope), dt)  # no exposure outlasts its frame

    def exposure_s(self) -> float:
        """The estimate [s]; 0 until the data fix it."""
        return self._e
