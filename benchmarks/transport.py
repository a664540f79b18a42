"""Zenoh transport between two processes: 1 ms EventPackets at a chosen offered load.

The sender is this process; the receiver is a separate process running the real ETAM `Service`
input path (zenoh callback -> bounded fifo -> asyncio -> decode), so the figures are what a service
sees: delivered messages and events per second, loss, and latency from `sent` to decoded. The
unpaced run is set beside dv-processing's NetworkWriter -> NetworkReader between two processes and
its numpy -> EventStore ingest, on packets of the same shape (its EventStores built before timing).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import time

import numpy as np
import zenoh

from benchmarks import free_port
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


def _dv_sink_main(port: int, expected: int) -> int:
    """dv-processing's NetworkReader: counts events until `expected` arrived; prints a JSON summary."""
    import dv_processing as dv

    for _ in range(200):
        try:
            reader = dv.io.NetworkReader("127.0.0.1", port)
            break
        except RuntimeError:
            time.sleep(0.05)
    n, first, last = 0, 0.0, 0.0
    deadline = time.monotonic() + 60
    while n < expected and time.monotonic() < deadline:
        batch = reader.getNextEventBatch()
        if batch is None:
            time.sleep(0.0002)
            continue
        last = time.monotonic()
        first = first or last
        n += len(batch)
    print(json.dumps({"events": n, "span_s": last - first}), flush=True)
    return 0


def _packets(count: int, per_packet: int) -> list[np.ndarray]:
    """`count` packets of `per_packet` events on a 346x260 sensor, 1 ms each."""
    rng = np.random.default_rng(0)
    out = []
    for i in range(count):
        ev = np.zeros(per_packet, EVENT_DTYPE)
        ev["x"], ev["y"] = rng.integers(0, 346, per_packet), rng.integers(0, 260, per_packet)
        ev["p"] = rng.integers(0, 2, per_packet)
        ev["t"] = i * 1000 + np.arange(per_packet) * 1000 // per_packet
        out.append(ev)
    return out


def dv_peer(count: int = 300, per_packet: int = 20_000) -> dict:
    """The peers' figures on the same kind of packets: dv-processing's numpy -> EventStore rate, and its
    NetworkWriter -> NetworkReader between two processes (events/s received, complete or not); ETAM's
    numpy -> EventPacket bytes rate beside the first."""
    from benchmarks.filters import dv_stores

    packets = _packets(count, per_packet)
    n = count * per_packet
    t0 = time.perf_counter()
    for i, ev in enumerate(packets):
        EventPacket(seq=i + 1, stamp=(i + 1) * 1000, width=346, height=260, events=ev).encode()
    etam_ingest = n / (time.perf_counter() - t0)
    try:
        import dv_processing as dv
    except ImportError as exc:
        return {"etam_ingest_events_per_s": etam_ingest, "peer_error": f"not installed ({exc.name})"}
    t0 = time.perf_counter()
    stores = dv_stores(packets)
    dv_ingest = n / (time.perf_counter() - t0)
    port = free_port()
    writer = dv.io.NetworkWriter("127.0.0.1", port, dv.io.Stream.EventStream(0, "events", "bench", (346, 260)))
    sink = subprocess.Popen([sys.executable, "-m", "benchmarks.transport", "dv-sink", str(port), str(n)],
                            stdout=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while writer.getClientCount() < 1 and time.monotonic() < deadline:
            time.sleep(0.01)
        for store in stores:
            writer.writeEvents(store)
        out, _ = sink.communicate(timeout=120)
    finally:
        if sink.poll() is None:
            sink.kill()
        del writer
    got = json.loads(out.strip().splitlines()[-1])
    return {"etam_ingest_events_per_s": etam_ingest, "peer_ingest_events_per_s": dv_ingest,
            "peer_events_per_s": got["events"] / max(got["span_s"], 1e-6), "peer_complete": got["events"] == n,
            "peer_error": None}


def _sink_main(endpoint: str) -> int:
    opts = ServiceOptions(rig="bench", name="sink", zenoh=ZenohSettings(mode="peer", listen=[endpoint]))
    return Sink(opts).run()


def run_load(events_per_s: float | None, duration_s: float, endpoint: str, saturate_per_packet: int = 20_000) -> dict:
    """Offer `events_per_s` in 1 ms packets for `duration_s`, or with None send packets of
    `saturate_per_packet` events as fast as the sender can (capacity); the receiver's figures."""
    paced = events_per_s is not None
    per_packet = int(round(events_per_s / 1000)) if paced else saturate_per_packet
    (ev,) = _packets(1, per_packet)
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


def run(loads: tuple[float | None, ...] = (1e6, 5e6, 20e6, None), duration_s: float = 3.0,
        peer_packets: int = 300) -> list[dict]:
    """One result per offered load (events/s; None: as fast as possible); the unpaced one beside
    dv-processing's network transport and numpy ingest on packets of the same shape."""
    rows = [run_load(load, duration_s, f"tcp/127.0.0.1:{free_port()}") for load in loads]
    for row in rows:
        if row["offered_events_per_s"] == "max":
            peer = dv_peer(peer_packets, row["events_per_packet"])
            row.update(peer=("dv-processing NetworkWriter -> NetworkReader", "numpy -> EventStore"), **peer)
            if peer.get("peer_events_per_s"):
                row["ratio"] = row["events_per_s"] / peer["peer_events_per_s"]
                row["ingest_ratio"] = peer["etam_ingest_events_per_s"] / peer["peer_ingest_events_per_s"]
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="transport benchmark receiver (started by etam bench)")
    parser.add_argument("role", choices=["sink", "dv-sink"])
    parser.add_argument("endpoint", help="zenoh endpoint (sink) or TCP port (dv-sink)")
    parser.add_argument("expected", nargs="?", type=int, default=0, help="events to wait for (dv-sink)")
    args = parser.parse_args()
    sys.exit(_sink_main(args.endpoint) if args.role == "sink" else _dv_sink_main(int(args.endpoint), args.expected))
