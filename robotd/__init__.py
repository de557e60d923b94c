"""robotd: an onboard stereo-vision SLAM daemon (EKF SLAM, FastSLAM 1.0 and 2.0).

The thesis this implements: W. Brink, *Stereo vision for simultaneous localization and mapping*,
MSc thesis, Stellenbosch University, 2012.
"""

from __future__ import annotations

__version__ = "0.1.0"
