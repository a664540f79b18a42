"""Where the targets sharing one blob are: boxes of known sizes placed to explain its recent pixels.

When targets cross or walk side by side, their events form one blob and its box is the union of
theirs. The tracks still know each target's size, so each box is moved (coordinate ascent over
integer shifts near its prediction) to cover as many recent pixels as it can that no other box
already explains, and as little empty image: a pixel gains `1 - density` if it fired recently and
loses `density` if not. Pixels under another box count for nothing, so a target partly hidden
behind a nearer one is placed by the part of it still in view, and one wholly inside another's box
stays at its prediction, held there by a small pull.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class LayoutParams:
    recent: float = 0.35  # decayed weight of a pixel that fired recently (as the cluster boxes use)
    density: float = 0.1  # share of recent pixels above which covering a pixel pays
    reach_px: int = 6  # each box moves at most this far from its prediction per round
    pull: float = 0.2  # cost of a box's squared shift from its prediction, per px^2
    rounds: int = 2


def fit_layout(image: np.ndarray, boxes: np.ndarray, params: LayoutParams) -> np.ndarray:
    """The boxes (K x 4: x, y, w, h, sizes kept) moved onto the recent pixels of a decayed image."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    h_img, w_img = image.shape
    r = params.reach_px
    x0 = max(int(np.floor(boxes[:, 0].min())) - r * params.rounds, 0)
    y0 = max(int(np.floor(boxes[:, 1].min())) - r * params.rounds, 0)
    x1 = min(int(np.ceil((boxes[:, 0] + boxes[:, 2]).max())) + r * params.rounds, w_img)
    y1 = min(int(np.ceil((boxes[:, 1] + boxes[:, 3]).max())) + r * params.rounds, h_img)
    if x1 <= x0 or y1 <= y0:
        return boxes.astype(np.float32)
    gain = (image[y0:y1, x0:x1] >= params.recent).astype(np.float32) - np.float32(params.density)
    pred = boxes.copy()
    pos = np.round(boxes[:, :2]).astype(np.int64) - (x0, y0)
    size = np.maximum(np.round(boxes[:, 2:]).astype(np.int64), 1)
    shifts = np.arange(-r, r + 1)
    for _ in range(params.rounds):
        for k in range(len(boxes)):
            own = gain.copy()
            for j in range(len(boxes)):
                if j != k:
                    own[max(pos[j, 1], 0):max(pos[j, 1] + size[j, 1], 0),
                        max(pos[j, 0], 0):max(pos[j, 0] + size[j, 0], 0)] = 0
            total = cv2.integral(own)
            xs = np.clip(pos[k, 0] + shifts, 0, None)
            ys = np.clip(pos[k, 1] + shifts, 0, None)
            xa, xb = np.clip(xs, 0, own.shape[1]), np.clip(xs + size[k, 0], 0, own.shape[1])
            ya, yb = np.clip(ys, 0, own.shape[0])[:, None], np.clip(ys + size[k, 1], 0, own.shape[0])[:, None]
            covered = total[yb, xb] - total[ya, xb] - total[yb, xa] + total[ya, xa]
            dx = xs + x0 - pred[k, 0]
            dy = (ys + y0 - pred[k, 1])[:, None]
            score = covered - params.pull * (dx * dx + dy * dy)
            iy, ix = np.unravel_index(int(np.argmax(score)), score.shape)
            pos[k] = xs[ix], ys[iy]
    out = boxes.copy()
    out[:, :2] = pos + (x0, y0)
    moved = np.any(out[:, :2] != np.round(pred[:, :2]), axis=1)
    out[~moved, :2] = pred[~moved, :2]  # no better place: keep the sub-pixel prediction
    return out.astype(np.float32)
