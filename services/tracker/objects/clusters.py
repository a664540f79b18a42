"""Moving clusters in a decayed event image: local density threshold, then connected components.

Seed 003 compares contour- and feature-based clustering; this is the contour family: smoothing the
count image into a density, keeping pixels dense enough to be an object rather than sensor noise,
closing gaps inside an object, and taking each connected region as one detection.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class ClusterParams:
    density: float = 0.25  # decayed events per pixel, averaged over `window_px`
    window_px: int = 7
    close_px: int = 9
    min_area_px: int = 60


def detect_clusters(image: np.ndarray, params: ClusterParams) -> tuple[np.ndarray, np.ndarray]:
    """Boxes (N x 4: x, y, w, h) and masses (decayed event count) of the moving clusters in `image`."""
    density = cv2.blur(image, (params.window_px, params.window_px))
    mask = (density > params.density).astype(np.uint8)
    if params.close_px > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.close_px, params.close_px))
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    keep = np.flatnonzero(stats[1:, cv2.CC_STAT_AREA] >= params.min_area_px) + 1
    boxes = stats[keep, :4].astype(np.float32)
    mass = np.bincount(labels.ravel(), image.ravel(), n)[keep].astype(np.float32)
    return boxes, mass
