"""Synthetic test images shared by the front end's tests."""

from __future__ import annotations

import cv2
import numpy as np


def smooth_texture(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A smooth random texture (blurred noise), the kind of surface stereo refinement works on."""
    img = cv2.GaussianBlur(rng.uniform(0, 255, (h, w)).astype(np.float32), (0, 0), 1.5)
    img = (img - img.min()) / (img.max() - img.min()) * 255.0
    return img
