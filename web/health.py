"""What the dashboard knows of every service's health: its last Stats, its liveliness, what changed
since the Stats before (new drops, new malformed messages), and short histories for the plots.

Pure Python: the service feeds it messages and liveliness changes; it gives a markdown table and plot
series."""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

import numpy as np

from services import keys
from services.messages import Stats

SILENT_S = 3.0  # Stats come once a second: three missed is silence
FORGET_S = 30.0  # a service gone (no token, no Stats) this long leaves the table
HISTORY_S = 120.0  # the plots' span
SLOW_P99_MS = 50.0  # an input whose p99 latency is above this is flagged
BUSY_CPU = 90.0  # percent of one core


@dataclass
class ServiceHealth:
    """One service instance: its last two Stats, when the last came, whether its token is alive."""

    stats: Stats | None = None
    previous: Stats | None = None
    seen_s: float = 0.0
    alive: bool | None = None  # None: no liveliness news yet
    gone_s: float | None = None  # when its token went

    def flags(self, now_s: float) -> list[str]:
        """Why this service looks unhealthy, worst first; empty when it is fine."""
        out = []
        if self.alive is False:
            out.append("gone")
        elif self.stats is None:
            out.append("no Stats yet")
        elif now_s - self.seen_s > SILENT_S:
            out.append("silent")
        if self.stats is None:
            return out
        new_drops = _total(self.stats, "dropped") - (_total(self.previous, "dropped") if self.previous else 0)
        new_bad = _total(self.stats, "malformed") - (_total(self.previous, "malformed") if self.previous else 0)
        if new_drops > 0:
            out.append(f"dropping ({new_drops} in 1 s)")
        if new_bad > 0:
            out.append(f"malformed input ({new_bad} in 1 s)")
        p99 = [r["latency_p99_ms"] for r in self.stats.keys if r.get("latency_p99_ms") is not None]
        if p99 and max(p99) > SLOW_P99_MS:
            out.append(f"slow (p99 {max(p99):.0f} ms)")
        if self.stats.cpu_percent > BUSY_CPU:
            out.append("busy")
        return out


def _total(stats: Stats | None, field_name: str) -> int:
    return sum(int(r.get(field_name) or 0) for r in stats.keys) if stats else 0


@dataclass
class Health:
    """Every service of one rig, by ``service/name``, and the rig's event rate and latency over time."""

    services: dict[str, ServiceHealth] = field(default_factory=dict)
    history: collections.deque = field(default_factory=lambda: collections.deque(maxlen=int(HISTORY_S) * 2))

    def on_stats(self, msg: Stats, now_s: float) -> None:
        sh = self.services.setdefault(f"{msg.service}/{msg.name}", ServiceHealth())
        sh.previous, sh.stats, sh.seen_s = sh.stats, msg, now_s
        if sh.alive is False:  # Stats after the token went: it came back
            sh.alive, sh.gone_s = True, None

    def on_liveliness(self, key: str, alive: bool, now_s: float) -> None:
        parts = keys.parse(key)
        if parts is None:
            return
        sh = self.services.setdefault(f"{parts[1]}/{parts[2]}", ServiceHealth(seen_s=now_s))
        sh.alive, sh.gone_s = alive, (None if alive else now_s)

    def sample(self, now_s: float) -> None:
        """Append one point to the plots' history: events per second out of cameras, worst input p99."""
        rate, p99 = 0.0, 0.0
        for sh in self.services.values():
            if sh.stats is None or sh.alive is False or now_s - sh.seen_s > SILENT_S:
                continue
            for row in sh.stats.keys:
                if row["dir"] == "out" and str(row["key"]).endswith("/events"):
                    rate += float(row["event_rate"])
                if row["dir"] == "in" and row.get("latency_p99_ms") is not None:
                    p99 = max(p99, float(row["latency_p99_ms"]))
        self.history.append((now_s, rate, p99))

    def series(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Seconds relative to now (<= 0), event rate (Mev/s), worst p99 latency (ms)."""
        if not self.history:
            return np.zeros(1), np.zeros(1), np.zeros(1)
        arr = np.asarray(self.history, np.float64)
        return arr[:, 0] - arr[-1, 0], arr[:, 1] / 1e6, arr[:, 2]

    def forget(self, now_s: float) -> None:
        """Drop services long gone, so a restarted rig's table does not fill with ghosts."""
        for who in [w for w, sh in self.services.items()
                    if now_s - max(sh.seen_s, sh.gone_s or 0.0) > FORGET_S and (sh.alive is not True)]:
            del self.services[who]

    def markdown(self, now_s: float) -> str:
        """A table: a line per service (flags in bold), then its inputs and outputs with rates, lost
        messages, malformed ones and latency."""
        if not self.services:
            return "*No services seen yet.*"
        lines = ["| key | msg/s | ev/s | lost | bad | p99 ms |", "|---|---:|---:|---:|---:|---:|"]
        for who in sorted(self.services):
            sh = self.services[who]
            flags = sh.flags(now_s)
            mark = "🔴" if flags else "🟢"
            flag_text = f" · **{', '.join(flags)}**" if flags else ""
            usage = f" · {sh.stats.cpu_percent:.0f}% cpu · {sh.stats.rss_bytes / 2**20:.0f} MB" if sh.stats else ""
            lines.append(f"| {mark} **{who}**{usage}{flag_text} ||||||")
            for row in (sh.stats.keys if sh.stats and sh.alive is not False else []):
                p99 = row.get("latency_p99_ms")
                arrow = "→" if row["dir"] == "out" else "←"
                lines.append(
                    f"| {arrow} {_short_key(str(row['key']), who)} "
                    f"| {row['msg_rate']:.0f} | {_si(row['event_rate'])} | {row['dropped']} | {row['malformed']} "
                    f"| {'' if p99 is None else f'{p99:.1f}'} |"
                )
        return "\n".join(lines)


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
