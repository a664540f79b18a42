"""Seed 003's feature method: corners of the accumulated image, grouped into clusters.

Corners (Shi-Tomasi) keep the textured, dense parts of the image and drop sparse noise; corners
closer than `link_px` are linked into one cluster, and each cluster of enough corners is a box.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.tracker.objects.accumulator import to_uint8


@dataclass
class CornerParams:
    max_corners: int = 400
    quality: float = 0.05
    min_distance_px: int = 3
    link_px: int = 12
    min_corners: int = 6


def detect_corner_clusters(image: np.ndarray, params: CornerParams) -> np.ndarray:
    """Boxes (N x 4: x, y, w, h) of the corner clusters of a decayed event image."""
    pts = cv2.goodFeaturesToTrack(to_uint8(image), params.max_corners, params.quality, params.min_distance_px)
    if pts is None:
        return np.zeros((0, 4), np.float32)
    pts = pts.reshape(-1, 2)
    canvas = np.zeros(image.shape, np.uint8)
    xy = np.round(pts).astype(np.int32)
    canvas[xy[:, 1], xy[:, 0]] = 1
    linked = cv2.dilate(canvas, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (params.link_px, params.link_px)))
    _, labels = cv2.connectedComponents(linked, connectivity=8)
    lab = labels[xy[:, 1], xy[:, 0]]
    boxes = []
    for k in np.unique(lab):
        sel = pts[lab == k]
        if len(sel) >= params.min_corners:
            lo, hi = sel.min(axis=0), sel.max(axis=0)
            boxes.append([lo[0], lo[1], hi[0] - lo[0] + 1, hi[1] - lo[1] + 1])
    return np.asarray(boxes, np.float32).reshape(-1, 4)
