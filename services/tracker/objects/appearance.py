"""What each target looks like in the decayed image, to find it again among others (seed 002's template).

Where targets share a blob, the layout (`layout.py`) knows only which pixels fired, not whose they are:
two boxes over one union of pixels fit it about as well in many places, and a small pull towards the
predictions decides. The pixels' pattern does tell them apart: a textured target moving on a steady
course fires the same pattern of edges update after update. So a confirmed track keeps a copy of the
image in its box while it has a detection of its own (its template), and where it shares a blob the
template is searched for near its prediction by normalised cross-correlation. Seed 002 matches its
template with learnt (Siamese) features; no weights can ship here, so the patch itself is the feature,
shrunk (events are sparse: means over 2 x 2 pixels or more of a clipped image are smoother to correlate).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from services.tracker.objects.association import Box


@dataclass
class AppearanceParams:
    reach_px: int = 6  # the template is searched this far around the prediction (0: off)
    # the best match counts if its correlation is this high (0.35 and 0.65 made more id switches, below)
    min_score: float = 0.5
    # a patch is correlated shrunk 2 times, or 4, 8... until its longer side is at most this: a big target's pattern
    # at 2 x 2 changes more as it moves than its coarser one does. On four sets of 60 seeds id switches per
    # object-minute 1.85 with no limit, 1.81 at 16, 1.79 at 24, 1.81 at 32 (and the fewer pixels, the faster)
    max_side_px: int = 24


def template(image: np.ndarray, box: Box) -> np.ndarray | None:
    """A copy of the decayed `image` in `box` (even sizes), or None where the box is not wholly inside the image
    or too small. Taken at every update a track is seen on its own, and used only where it comes to share a
    blob: `find` shrinks it then."""
    h, w = image.shape
    x0, y0 = int(round(box[0])), int(round(box[1]))
    bw, bh = int(round(box[2])) // 2 * 2, int(round(box[3])) // 2 * 2
    if x0 < 0 or y0 < 0 or x0 + bw > w or y0 + bh > h or bw < 8 or bh < 8:
        return None
    return image[y0:y0 + bh, x0:x0 + bw].copy()


def find(image: np.ndarray, patch: np.ndarray, box: Box, params: AppearanceParams) -> tuple[float, float] | None:
    """The shift (dx, dy, px) from `box` (a prediction) to where `patch` (a `template`, centred on it) matches the
    image best within `reach_px`, at half size and to sub-pixel by a parabola through the correlations. None where
    the patch is plain, the search would leave the image or the best match is poor. The whole patch is correlated,
    with the pixels of a nearer target that hides part of it: leaving out those under the other tracks' boxes (a
    mask) changed nothing on four sets of 60 seeds, at twice the time."""
    if params.reach_px <= 0:
        return None
    scale = 2  # events are sparse: means over 2 x 2 pixels (or more, for a big patch) are smoother to correlate
    while max(patch.shape) > params.max_side_px * scale:
        scale *= 2
    ph, pw = patch.shape[0] // scale, patch.shape[1] // scale
    r = -(-params.reach_px // scale)  # the reach in shrunk pixels, rounded up
    cx, cy = box[0] + box[2] / 2, box[1] + box[3] / 2
    x0, y0 = int(round(cx - pw * scale / 2)) - r * scale, int(round(cy - ph * scale / 2)) - r * scale
    h, w = image.shape
    if x0 < 0 or y0 < 0 or x0 + (pw + 2 * r) * scale > w or y0 + (ph + 2 * r) * scale > h:
        return None
    score, fx, fy = _best(image, patch, x0, y0, scale, r)
    if score < params.min_score:
        return None
    return x0 + (fx + pw / 2) * scale - cx, y0 + (fy + ph / 2) * scale - cy


@numba.njit(cache=True, nogil=True)
def _best(image, patch, x0, y0, scale, r):  # noqa: ANN001, ANN202 - numba kernel
    """The best of `_correlations` and where it is (shrunk pixels from (x0, y0)), to sub-pixel by a parabola through
    it and its neighbours on each axis."""
    scores = _correlations(image, patch, x0, y0, scale, r)
    at = np.argmax(scores)
    by, bx = at // scores.shape[1], at % scores.shape[1]
    fx, fy = float(bx), float(by)
    if 0 < bx < scores.shape[1] - 1:
        fx += _vertex(scores[by, bx - 1], scores[by, bx], scores[by, bx + 1])
    if 0 < by < scores.shape[0] - 1:
        fy += _vertex(scores[by - 1, bx], scores[by, bx], scores[by + 1, bx])
    return scores[by, bx], fx, fy


@numba.njit(cache=True, nogil=True)
def _vertex(a, b, c):  # noqa: ANN001, ANN202 - numba kernel
    """The offset of the top of the parabola through three scores from the middle one (0 if it has none)."""
    curve = a - 2 * b + c
    return 0.5 * (a - c) / curve if curve < 0 else 0.0


@numba.njit(cache=True, nogil=True)
def _correlations(image, patch, x0, y0, scale, r):  # noqa: ANN001, ANN202 - numba kernel
    """Normalised cross-correlations (OpenCV's TM_CCOEFF_NORMED) of `patch` with the image from (x0, y0), both
    shrunk `scale` times (`_shrunk`), at shifts of 0 to 2r shrunk pixels on each axis: (2r + 1) x (2r + 1), -1 where
    the image or the patch is plain. As one kernel: OpenCV's resize and matchTemplate cost some 40 us a call on
    patches this small, most of it in their setting up."""
    ph, pw = patch.shape[0] // scale, patch.shape[1] // scale
    t = _shrunk(patch, 0, 0, ph, pw, scale)
    g = _shrunk(image, x0, y0, ph + 2 * r, pw + 2 * r, scale)
    t -= t.mean()
    t_norm = np.sqrt((t * t).sum())
    out = np.full((2 * r + 1, 2 * r + 1), -1.0)
    if t_norm <= 1e-6:
        return out
    gh, gw = g.shape  # sums and sums of squares of the image's windows from integral images: one product a pixel
    total, squares = np.zeros((gh + 1, gw + 1)), np.zeros((gh + 1, gw + 1))
    for y in range(gh):
        for x in range(gw):
            v = g[y, x]
            total[y + 1, x + 1] = total[y, x + 1] + total[y + 1, x] - total[y, x] + v
            squares[y + 1, x + 1] = squares[y, x + 1] + squares[y + 1, x] - squares[y, x] + v * v
    n = ph * pw
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            c = 0.0
            for y in range(ph):
                for x in range(pw):
                    c += g[dy + y, dx + x] * t[y, x]
            s = total[dy + ph, dx + pw] - total[dy, dx + pw] - total[dy + ph, dx] + total[dy, dx]
            s2 = squares[dy + ph, dx + pw] - squares[dy, dx + pw] - squares[dy + ph, dx] + squares[dy, dx]
            var = s2 - s * s / n
            if var > 1e-9:
                out[dy, dx] = c / (np.sqrt(var) * t_norm)
    return out


@numba.njit(cache=True, nogil=True)
def _shrunk(image, x0, y0, h, w, scale):  # noqa: ANN001, ANN202 - numba kernel
    """The h x w means of the image clipped at 3 events over squares of `scale` pixels from (x0, y0)."""
    out = np.empty((h, w))
    for oy in range(h):
        for ox in range(w):
            total = 0.0
            for y in range(y0 + oy * scale, y0 + (oy + 1) * scale):
                for x in range(x0 + ox * scale, x0 + (ox + 1) * scale):
                    total += min(image[y, x], 3.0)
            out[oy, ox] = total
    return out / (scale * scale)


def warm_up() -> None:
    """Loads the kernels (see `tracker.warm_up`): its warm-up scene may not make a track find its template."""
    image = np.zeros((32, 32), np.float32)
    image[8:16, 8:16] = np.arange(64, dtype=np.float32).reshape(8, 8) / 32
    patch = template(image, (8.0, 8.0, 8.0, 8.0))
    if patch is not None:
        find(image, patch, (9.0, 8.0, 8.0, 8.0), AppearanceParams())
