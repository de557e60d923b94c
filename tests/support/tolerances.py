"""The numerical tolerances the tests share, each named once with the error it bounds.

Only tolerances that stand for a shared idea are here: float64 round-off of a closed form, a numba
kernel against its numpy twin, central-difference Jacobians, float32 storage and arithmetic, and the
resolution of an angle taken from its cosine. A bound that belongs to one scenario (an ATE limit on
KITTI, a statistical band, an iterative solver's stopping rule) stays a named constant in its test,
with its reason there.

Units: EPS is float64's machine epsilon, the spacing of doubles at 1.0 (2.2e-16); a correctly
rounded operation is off by at most EPS/2 relative. EPS32 is float32's (1.2e-7).
"""

from __future__ import annotations

import math

import numpy as np

EPS = float(np.finfo(np.float64).eps)  # 2.220446049250313e-16
EPS32 = float(np.finfo(np.float32).eps)  # 1.1920929e-07

# ------------------------------------------------------------------ float64 round-off

ULP_ATOL = 1e-15
"""The same float64 expression evaluated two ways that differ only in batching, memory layout or
the association of a few operations, on O(1) values (e.g. one pose at a time vs a batch, a closed
form vs the product it expands): a few ulps. 1e-15 is 4.5 EPS."""

ROUNDOFF_ATOL = 1e-12
"""A short closed form or identity in float64 (R Rᵀ = I, T T⁻¹ = I, a round trip through another
representation, a matrix update written two ways) on values up to ~10: tens of operations each off
by ≤ EPS/2, i.e. ~1e-14. 1e-12 keeps a ~100× margin and is still ≥ 1e6 below any modelling error
the tests look for. Also the round-off allowance when asserting a covariance is PSD (smallest
eigenvalue > −ROUNDOFF_ATOL)."""

ROUNDOFF_RTOL = 1e-12
"""ROUNDOFF_ATOL as a relative tolerance, for the same kind of computation on values of any size."""

CONDITIONED_ATOL = 1e-9
"""Exact in exact arithmetic, but computed through a long chain or a conditioned step: an SVD
(Umeyama, trajectory alignment, the 8-point rank), arcsin/atan2/arccos away from their singular
points, linear solves with covariances, an estimator or an integrator fed noiseless data over tens
to hundreds of steps, values up to ~100. Round-off there is EPS × condition × magnitude, ≲ 1e-11 in
the tests' cases; 1e-9 keeps ≥ 100× margin and is still ≥ 1e3 below any modelling error looked for.
Also the guard when a computed value is compared with an exact boundary (≤ d_max + 1e-9)."""

CONDITIONED_RTOL = 1e-9
"""CONDITIONED_ATOL as a relative tolerance (Mahalanobis distances, focal lengths, baselines)."""

# ------------------------------------------------------------------ numba kernels and their twins

KERNEL_TWIN_ATOL = 1e-9
"""A numba kernel against its readable numpy twin in tests/support/reference_*.py, given the same
inputs and the same random draws (``eps``): the same mathematics in a different operation order,
with hand-written 2×2/3×3 inverses and Cholesky factors against LAPACK's. Round-off of ~1e-13 per
step, amplified by covariance conditioning over a few updates (measured ≤ 1e-11 over the FastSLAM
cases); 1e-9 is far above that and far below what a wrong index or branch gives (≥ 1e-3)."""

KERNEL_TWIN_RTOL = 1e-10
"""A non-iterative kernel against its twin, relative: the outlier stage's squared Mahalanobis
distances span many decades, so agreement is relative (measured ≤ 1e-14 relative)."""

# ------------------------------------------------------------------ derivatives

CENTRAL_DIFF_ATOL = 1e-6
"""An analytic Jacobian against robotd.core.geometry.numerical_jacobian (central differences, default
step h = 1e-6): truncation h²/6·|f'''| ≈ 2e-13·|f'''| plus round-off EPS·|f|/h ≈ 2e-10·|f|. For
the O(1)…O(10) functions tested that is ≤ ~2e-9 (measured ≤ 1.8e-9); 1e-6 is a ≥ 500× margin and
still far below the error of a wrong sign or a missing term (O(0.1))."""

# ------------------------------------------------------------------ float32

FLOAT32_ROUNDING_TOL = 1e-6
"""A value that was rounded to float32 once (the map file, the MCU's and MAVLink's wire fields,
depthai's float32 calibration): off by ≤ EPS32/2 ≈ 6e-8 relative, so ≤ 6e-7 for values up to ~10.
Used as rtol, or as atol for O(1) values; 1e-6 is the bound with a small margin."""

FLOAT32_ARITH_TOL = 1e-5
"""Float32 results against a float64 reference when more than one rounding separates them: float32
arithmetic (the renderer's inverse-depth plane a x + b y + c, distances between float32
descriptors, a difference of two float32 wheel speeds) or float64 work stored in float32 whose twin
orders its sums differently (SURF's response maps and descriptors). A few to tens of ulps of EPS32
(1.2e-7); 1e-5 is ~84 EPS32 (measured: SURF maps 5.9e-8 relative, descriptors 3.5e-7). Used as rtol,
or as atol for O(1) values."""


# ------------------------------------------------------------------ angles from a cosine

COSINE_ROUNDOFF = 16 * EPS
"""How far round-off can move the cosine c = (tr R − 1)/2 of a rotation matrix R formed from a few
float64 rotations (the evaluation's error rotation Q⁻¹ · T · P, with T from an SVD). Each diagonal
entry of a 3×3 product of orthonormal matrices is a 3-term dot product of unit vectors, off by
≤ γ₃ ≈ 1.5 EPS (Higham's bound, u = EPS/2) per product; the factors are themselves orthonormal only
to a few EPS; the trace adds three entries, (· − 1)/2 halves the sum: ≲ 13 EPS in the worst case.
Measured on x86-64: ≤ 3 EPS. 16 EPS covers the worst case on any IEEE-754 machine (FMA or not,
any BLAS kernel)."""

ANGLE_FROM_COSINE_FLOOR_RAD = math.sqrt(2.0 * COSINE_ROUNDOFF)  # 8.4e-8 rad
"""The smallest angle arccos can report for a rotation that is the identity up to round-off:
arccos(1 − δ) ≈ √(2δ), so a cosine COSINE_ROUNDOFF below 1 reads as √(32 EPS) ≈ 8.4e-8 rad. The
floor is of the method, not of the data: the next double below 1 (δ = EPS/2) already reads as
1.5e-8 rad, δ = EPS as 2.1e-8 rad = 1.2e-6 deg, which is why "heading RMSE < 1e-6 deg" after a
rigid motion held on one CPU only. The same holds near π: arccos(−1 + δ) = π − √(2δ), so angles
within ~1e-8 rad of π come back as exactly π (robotd.core.geometry.so3_log). Rotation matrix entries
move by at most the angle error, so this bounds them too. A real alignment or rotation error is
orders of magnitude larger."""

ANGLE_FROM_COSINE_FLOOR_DEG = math.degrees(ANGLE_FROM_COSINE_FLOOR_RAD)  # 4.8e-6 deg
"""ANGLE_FROM_COSINE_FLOOR_RAD in degrees, for metrics reported in degrees (heading RMSE, RPE)."""
