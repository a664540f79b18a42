"""Pictures for the dashboard: event frames with boxes, colour maps, any Image made viewable (pure numpy / cv2).

Images here are RGB, as the browser shows them."""

from __future__ import annotations

import cv2
import numba
import numpy as np

from services.messages import Tracks

# bright enough in luma to survive JPEG's halved chroma resolution
ON_RGB = np.array([255, 120, 110], np.float32)  # light red for ON
OFF_RGB = np.array([90, 210, 255], np.float32)  # light blue for OFF
STATE_NAMES = {0: "new", 1: "", 2: "lost"}


def _event_palette() -> np.ndarray:
    """The 9 colours of a pixel by its ON and OFF counts (0, 1, 2 or more each): ON blended over dark grey
    by half per event, then OFF over that."""
    out = np.empty((3, 3, 3), np.float32)
    for on in range(3):
        for off in range(3):
            a_on, a_off = on / 2.0, off / 2.0
            out[on, off] = (30 * (1 - a_on) + ON_RGB * a_on) * (1 - a_off) + OFF_RGB * a_off
    return out.reshape(9, 3).astype(np.uint8)


EVENT_PALETTE = _event_palette()


@numba.njit(cache=True, nogil=True)
def _event_image(x, y, p, width, height, palette):  # noqa: ANN001, ANN202 - numba kernel
    """Count each pixel's ON and OFF events (each saturating at 2) in one pass, then paint the palette."""
    on = np.zeros(width * height, np.uint8)
    off = np.zeros(width * height, np.uint8)
    for i in range(len(x)):
        if x[i] < width and y[i] < height:
            j = y[i] * width + x[i]
            if p[i] == 1:
                on[j] = min(on[j] + 1, 2)
            else:
                off[j] = min(off[j] + 1, 2)
    out = np.empty((width * height, 3), np.uint8)
    for j in range(width * height):
        k = on[j] * 3 + off[j]
        out[j, 0], out[j, 1], out[j, 2] = palette[k, 0], palette[k, 1], palette[k, 2]
    return out


def event_frame(events: np.ndarray, width: int, height: int) -> np.ndarray:
    """An RGB image of the events: ON red, OFF blue, brighter with more events, on dark grey."""
    return _event_image(events["x"], events["y"], events["p"], width, height, EVENT_PALETTE).reshape(height, width, 3)


def track_colour(ident: int) -> tuple[int, int, int]:
    hue = (ident * 47) % 180
    rgb = cv2.cvtColor(np.uint8([[[hue, 200, 255]]]), cv2.COLOR_HSV2RGB)[0, 0]
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


def draw_tracks(img: np.ndarray, tracks: list[Tracks], truth: list[Tracks], scale: int = 2) -> np.ndarray:
    """Upscale `img` and draw truth boxes (thin white) and tracked boxes (coloured by id, labelled)."""
    out = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    for msg in truth:
        for box in msg.box:
            x, y, w, h = (box * scale).astype(int)
            cv2.rectangle(out, (x, y), (x + w, y + h), (235, 235, 235), 1)
    for msg in tracks:
        for ident, box, state in zip(msg.id, msg.box, msg.state, strict=True):
            if state == Tracks.TENTATIVE:
                continue
            x, y, w, h = (box * scale).astype(int)
            colour = track_colour(int(ident))
            cv2.rectangle(out, (x, y), (x + w, y + h), colour, 1 if state == Tracks.LOST else 2)
            label = f"#{ident} {STATE_NAMES.get(int(state), '')}".strip()
            cv2.putText(out, label, (x, max(y - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return out


def colormap(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """RGB uint8 per value on the turbo map, `lo` blue to `hi` red."""
    level = np.clip((np.asarray(values, np.float32) - lo) * (255.0 / max(hi - lo, 1e-9)), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(level.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3)[:, ::-1].copy()


def viewable(pixels: np.ndarray) -> np.ndarray:
    """Any Image's pixels as RGB uint8: colour (BGR) as is, grey as grey, 16-bit stretched to its range,
    float (depth, time surfaces) on the colour map with unknown (NaN) black."""
    if pixels.ndim == 3:
        return np.ascontiguousarray(pixels[..., 2::-1]).astype(np.uint8)
    if pixels.dtype == np.uint8:
        return np.repeat(pixels[..., None], 3, axis=2)
    values = pixels.astype(np.float32)
    known = np.isfinite(values)
    if not known.any():
        return np.zeros((*pixels.shape, 3), np.uint8)
    lo, hi = np.percentile(values[known], (1, 99))
    if pixels.dtype == np.uint16:  # a 16-bit PNG (the mosaic): grey levels
        grey = np.clip((values - lo) * (255.0 / max(hi - lo, 1e-9)), 0, 255).astype(np.uint8)
        return np.repeat(grey[..., None], 3, axis=2)
    out = colormap(np.where(known, values, lo).ravel(), float(lo), float(hi)).reshape(*pixels.shape, 3)
    out[~known] = 0
    return out
