"""Pictures for the dashboard: event frames with boxes, the service table (pure numpy / cv2).

Images here are RGB, as the browser shows them."""

from __future__ import annotations

import cv2
import numpy as np

from services import keys
from services.messages import Stats, Tracks

# bright enough in luma to survive JPEG's halved chroma resolution
ON_RGB = np.array([255, 120, 110], np.float32)  # light red for ON
OFF_RGB = np.array([90, 210, 255], np.float32)  # light blue for OFF
STATE_NAMES = {0: "new", 1: "", 2: "lost"}


def event_frame(events: np.ndarray, width: int, height: int) -> np.ndarray:
    """An RGB image of the events: ON red, OFF blue, brighter with more events, on dark grey."""
    img = np.full((height, width, 3), 30, np.float32)
    if len(events):
        inside = (events["x"] < width) & (events["y"] < height)
        ev = events[inside]
        idx = ev["y"].astype(np.int64) * width + ev["x"]
        for pol, colour in ((1, ON_RGB), (0, OFF_RGB)):
            sel = ev["p"] == pol
            count = np.bincount(idx[sel], minlength=width * height).reshape(height, width)
            alpha = np.minimum(count, 2)[..., None] / 2.0
            img = img * (1 - alpha) + colour * alpha
    return img.astype(np.uint8)


def _colour(ident: int) -> tuple[int, int, int]:
    hue = (ident * 47) % 180
    rgb = cv2.cvtColor(np.uint8([[[hue, 200, 255]]]), cv2.COLOR_HSV2RGB)[0, 0]
    return int(rgb[0]), int(rgb[1]), int(rgb[2])


def draw_tracks(img: np.ndarray, tracks: Tracks | None, truth: Tracks | None, scale: int = 2) -> np.ndarray:
    """Upscale `img` and draw truth boxes (thin white) and tracked boxes (coloured by id, labelled)."""
    out = cv2.resize(img, (img.shape[1] * scale, img.shape[0] * scale), interpolation=cv2.INTER_NEAREST)
    if truth is not None:
        for box in truth.box:
            x, y, w, h = (box * scale).astype(int)
            cv2.rectangle(out, (x, y), (x + w, y + h), (235, 235, 235), 1)
    if tracks is not None:
        for ident, box, state in zip(tracks.id, tracks.box, tracks.state, strict=True):
            if state == 0:
                continue
            x, y, w, h = (box * scale).astype(int)
            colour = _colour(int(ident))
            cv2.rectangle(out, (x, y), (x + w, y + h), colour, 1 if state == 2 else 2)
            label = f"#{ident} {STATE_NAMES.get(int(state), '')}".strip()
            cv2.putText(out, label, (x, max(y - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX, 0.45, colour, 1, cv2.LINE_AA)
    return out


def _si(value: float) -> str:
    for scale, suffix in ((1e6, "M"), (1e3, "k")):
        if value >= scale:
            return f"{value / scale:.1f}{suffix}"
    return f"{value:.0f}"


def _short_key(key: str, who: str) -> str:
    """A service's own key as its topic (``events``); any other without ``etam/<rig>/``."""
    parts = keys.parse(key)
    if parts is not None and f"{parts[1]}/{parts[2]}" == who:
        return parts[3]
    return "/".join(key.split("/")[2:]).replace("*", "\\*")


def services_markdown(stats: dict[str, Stats], now_s: float, seen_s: dict[str, float]) -> str:
    """A markdown table of live services: a line per service, then its inputs and outputs with
    rates, lost messages, malformed ones and latency."""
    if not stats:
        return "*No services seen yet.*"
    lines = ["| key | msg/s | ev/s | lost | bad | p99 ms |", "|---|---:|---:|---:|---:|---:|"]
    for who in sorted(stats):
        st = stats[who]
        silent = " · **silent**" if now_s - seen_s.get(who, now_s) > 3 else ""
        lines.append(f"| **{who}** · {st.cpu_percent:.0f}% cpu · {st.rss_bytes / 2**20:.0f} MB{silent} ||||||")
        for row in st.keys:
            p99 = row.get("latency_p99_ms")
            arrow = "→" if row["dir"] == "out" else "←"
            lines.append(
                f"| {arrow} {_short_key(str(row['key']), who)} "
                f"| {row['msg_rate']:.0f} | {_si(row['event_rate'])} | {row['dropped']} | {row['malformed']} "
                f"| {'' if p99 is None else f'{p99:.1f}'} |"
            )
    return "\n".join(lines)
