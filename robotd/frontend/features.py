"""Feature sets shared by every detector (SIFT, SURF, ORB).

This module holds the data type; the detectors themselves live beside it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True, eq=False)
class Features:
    """Keypoints and descriptors of one image, as a struct of arrays.

    ``xy`` are pixel coordinates (column, row) with pixel centres at integers (OpenCV convention).
    ``desc`` is float32 (SIFT 128-D, SURF 64-D; Euclidean distance) or uint8 packed bits
    (ORB 32 bytes; Hamming distance) as ``binary`` says.
    """

    xy: np.ndarray  # (N, 2) float32 [px]
    size: np.ndarray  # (N,) float32 [px] feature diameter (OpenCV KeyPoint.size convention)
    angle: np.ndarray  # (N,) float32 [deg] orientation in [0, 360), -1 when not oriented
    response: np.ndarray  # (N,) float32 detector strength
    laplacian: np.ndarray  # (N,) int8 sign of the Hessian trace (SURF), 0 when unknown
    desc: np.ndarray  # (N, D) float32 or (N, 32) uint8
    binary: bool = False

    @property
    def n(self) -> int:
        return int(self.xy.shape[0])

    def subset(self, idx: np.ndarray) -> Features:
        """The features at ``idx`` (indices or boolean mask), in that order."""
        return Features(
            self.xy[idx],
            self.size[idx],
            self.angle[idx],
            self.response[idx],
            self.laplacian[idx],
            self.desc[idx],
            self.binary,
        )

    @staticmethod
    def empty(dim: int = 64, binary: bool = False) -> Features:
        return Features(
            np.zeros((0, 2), np.float32),
            np.zeros(0, np.float32),
            np.zeros(0, np.float32),
            np.zeros(0, np.float32),
            np.zeros(0, np.int8),
            np.zeros((0, dim), np.uint8 if binary else np.float32),
            binary,
        )
