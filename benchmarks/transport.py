"""Zenoh transport between two processes: 1 ms EventPackets at a chosen offered load.

The sender is this process; the receiver is a separate process running the real ETAM `Service`
input path (zenoh callback -> bounded fifo -> asyncio -> decode), so the figures are what a service
sees: delivered messages and events per second, loss, and latency from `sent` to decoded.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import socket
import subprocess
import sys
import time

import numpy as np
import zenoh

from services.config import ZenohSettings
from services.messages import EVENT_DTYPE, EventPacket
from services.runtime import Service, ServiceOptions

KEY = "etam/bench/camera/cam0/events"
IDLE_S = 1.5


class Sink(Service):
    """Counts what arrives; ends `IDLE_S` after the last packet and prints a JSON summary."""

    kind = "bench"

    async def main(self) -> None:
        inp = self.subscribe(KEY, EventPacket, policy="fifo", maxsize=4096)
        lat_ms: list[float] = []
        n_msgs = n_events = 0
        first = last = 0.0
        while True:
            try:
                _key, msg = await asyncio.wait_for(inp.__anext__(), IDLE_S if n_msgs else 60.0)
            except TimeoutError:
                break
            now = time.time_ns()
            last = time.monotonic()
            first = first or last
            n_msgs += 1
            n_events += len(msg.events)
            lat_ms.append((now - msg.sent) / 1e6)
        lat = np.asarray(lat_ms) if lat_ms else np.zeros(1)
        counter = inp.counter
        print(json.dumps({
            "messages": n_msgs, "events": n_events, "span_s": last - first,
            "latency_p50_ms": float(np.percentile(lat, 50)), "latency_p99_ms": float(np.percentile(lat, 99)),
            "dropped": counter.dropped,
        }), flush=True)


def _sink_main(endpoint: str) -> int:
    opts = ServiceOptions(rig="bench", name="sink", zenoh=ZenohSettings(mode="peer", listen=[endpoint]))
    return Sink(opts).run()


def run_load(events_per_s: float | None, duration_s: float, endpoint: str, saturate_per_packet: int = 20_000) -> dict:
    """Offer `events_per_s` in 1 ms packets for `duration_s`, or with None send packets of
    `saturate_per_packet` events as fast as the sender can (capacity); the receiver's figures."""
    paced = events_per_s is not None
    per_packet = int(round(events_per_s / 1000)) if paced else saturate_per_packet
    rng = np.random.default_rng(0)
    ev = np.zeros(per_packet, EVENT_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, 346, per_packet), rng.integers(0, 260, per_packet)
    ev["p"] = rng.integers(0, 2, per_packet)
    sink = subprocess.Popen([sys.executable, "-m", "benchmarks.transport", "sink", endpoint],
                            stdout=subprocess.PIPE, text=True)
    try:
        conf = ZenohSettings(mode="peer", connect=[endpoint]).zenoh_config()
        with zenoh.open(conf) as session:
            pub = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.BLOCK)
            time.sleep(1.0)  # let the sink subscribe
            n = int(duration_s * 1000)
            t0 = time.perf_counter()
            for i in range(n):
                wait = t0 + i / 1000 - time.perf_counter()
                if paced and wait > 0:
                    time.sleep(wait)
                ev["t"] = i * 1000 + np.arange(per_packet) * 1000 // max(per_packet, 1)
                pub.put(EventPacket(seq=i + 1, stamp=(i + 1) * 1000, width=346, height=260, events=ev).encode())
            send_s = time.perf_counter() - t0
            pub.undeclare()
            out, _ = sink.communicate(timeout=60)
    finally:
        if sink.poll() is None:
            sink.kill()
    got = json.loads(out.strip().splitlines()[-1])
    span = max(got["span_s"], 1e-6)
    return {
        "offered_events_per_s": events_per_s if paced else "max", "events_per_packet": per_packet,
        "sent_messages": n,
        "offered_achieved_msg_per_s": n / send_s,
        "messages_per_s": got["messages"] / span, "events_per_s": got["events"] / span,
        "received_messages": got["messages"], "lost_messages": n - got["messages"],
        "receiver_dropped": got["dropped"],
        "latency_p50_ms": got["latency_p50_ms"], "latency_p99_ms": got["latency_p99_ms"],
    }


def _free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def run(loads: tuple[float | None, ...] = (1e6, 5e6, 20e6, None), duration_s: float = 3.0) -> list[dict]:
    """One result per offered load (events/s; None: as fast as possible)."""
    return [run_load(load, duration_s, _free_endpoint()) for load in loads]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="transport benchmark receiver (started by etam bench)")
    parser.add_argument("role", choices=["sink"])
    parser.add_argument("endpoint")
    args = parser.parse_args()
    sys.exit(_sink_main(args.endpoint))
