"""The names of the selectable algorithms, defined once.

The configuration schema (robotd.config) offers them as choices and the modules that implement
them validate against them; this module imports nothing, so the config stays cheap to load. The
estimators' names are their registrations in robotd.slam.factory (``ESTIMATORS``).
"""

from __future__ import annotations

DETECTORS = ("orb", "sift", "surf")  # robotd.frontend.detectors
OUTLIER_METHODS = ("similarity_mahalanobis", "similarity_euclidean", "fundamental", "none")  # robotd.core.outliers
MEASUREMENTS = ("cartesian", "pixel")  # robotd.slam.models: triangulated points, or stereo pixels
# the fixed ceiling on FastSLAM particles (slam.n_particles; a saved map's particle count): far above
# what a frame period affords (docs/reliability.md), low enough that a typo cannot take the RAM
MAX_PARTICLES = 10_000
