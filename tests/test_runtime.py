"""The subscription queue policies of DESIGN.md section 6, fed from a foreign thread as zenoh does."""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np

from services.messages import EVENT_DTYPE, EventPacket, Tracks, decode
from services.runtime import YIELD_EVERY_S, Input
from services.stats import KeyCounter


def _packet(seq: int, n: int = 3) -> bytes:
    return EventPacket(seq=seq, stamp=seq * 1000, width=8, height=8, events=np.zeros(n, EVENT_DTYPE)).encode()


async def _drain(inp: Input, n: int) -> list[tuple[str, int]]:
    out = []
    for _ in range(n):
        key, msg = await asyncio.wait_for(inp.__anext__(), 5)
        out.append((key, msg.seq))
    return out


def _input(policy: str, maxsize: int = 4, expect: type | None = EventPacket) -> Input:
    return Input(asyncio.get_running_loop(), "k/*", expect, policy, maxsize, KeyCounter("k/*", "in"))


def test_fifo_drops_the_oldest_and_counts_it() -> None:
    async def main() -> None:
        inp = _input("fifo", maxsize=4)
        for seq in range(1, 11):
            inp.push("k/a", _packet(seq))
        assert await _drain(inp, 4) == [("k/a", s) for s in (7, 8, 9, 10)]
        assert inp.counter.overflow == 6 and inp.counter.dropped == 6  # the gap 1..6 is the overflow
        assert inp.counter.events == 12

    asyncio.run(main())


def test_latest_keeps_the_newest_per_key_without_counting_loss() -> None:
    async def main() -> None:
        inp = _input("latest")
        for seq in range(1, 6):
            inp.push("k/a", _packet(seq))
            inp.push("k/b", _packet(seq))
        got = await _drain(inp, 2)
        assert sorted(got) == [("k/a", 5), ("k/b", 5)]
        assert inp.counter.skipped == 8 and inp.counter.dropped == 0

    asyncio.run(main())


def test_lossless_blocks_the_producer_instead_of_dropping() -> None:
    async def main() -> None:
        inp = _input("lossless", maxsize=2)
        done = threading.Event()

        def produce() -> None:  # zenoh's thread: must wait for room, never drop
            for seq in range(1, 21):
                inp.push("k/a", _packet(seq))
            done.set()

        threading.Thread(target=produce, daemon=True).start()
        await asyncio.sleep(0.3)
        assert not done.is_set()  # blocked on the full queue
        got = await _drain(inp, 20)
        assert [s for _, s in got] == list(range(1, 21))
        assert inp.counter.dropped == 0

    asyncio.run(main())


def test_wakes_a_waiting_consumer_from_another_thread_and_skips_malformed() -> None:
    async def main() -> None:
        inp = _input("fifo", maxsize=64)

        def produce() -> None:
            time.sleep(0.2)
            inp.push("k/a", b"\x00garbage")
            inp.push("k/a", Tracks.from_boxes(0, [], []).encode())  # valid, wrong type
            inp.push("k/a", _packet(1))

        threading.Thread(target=produce, daemon=True).start()
        assert await _drain(inp, 1) == [("k/a", 1)]
        assert inp.counter.malformed == 2
        inp.close()
        try:
            await asyncio.wait_for(inp.__anext__(), 2)
            raise AssertionError("a closed, empty input must end the iteration")
        except StopAsyncIteration:
            pass

    asyncio.run(main())


def test_peek_reads_message_headers_without_the_arrays() -> None:
    import msgpack
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from services.messages import Stats, peek

    packet = EventPacket(seq=7, stamp=1, width=8, height=8, events=np.zeros(123, EVENT_DTYPE)).encode()
    assert peek(packet) == {"type": "EventPacket", "seq": 7, "count": 123, "sent": decode(packet).sent}
    assert peek(Tracks.from_boxes(0, [1, 2], [[0, 0, 1, 1], [1, 1, 1, 1]]).encode())["count"] == 2
    assert "count" not in peek(Stats(service="a", name="b", keys=[]).encode())

    values = st.recursive(st.none() | st.integers(-(2**63), 2**63 - 1) | st.text(max_size=4) | st.binary(max_size=8),
                          lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner,
                                                                                      max_size=3), max_leaves=8)

    @given(st.binary(max_size=64) | st.dictionaries(st.sampled_from(["type", "seq", "events", "id", "x"]), values,
                                                   max_size=4).map(msgpack.packb))
    @settings(max_examples=300, deadline=None)
    def garbage_is_refused_with_known_errors(payload: bytes) -> None:
        try:
            peek(payload)
        except (ValueError, TypeError, LookupError, msgpack.UnpackException):
            pass

    garbage_is_refused_with_known_errors()


def test_a_consumer_behind_its_input_still_lets_the_loop_run_other_tasks() -> None:
    """A backlog means every sample is ready at once; the input must still give the loop back, or the
    service's heartbeat (Stats) stops and the launcher takes it for hung."""
    async def main() -> None:
        inp = _input("fifo", maxsize=1000)
        for seq in range(1, 31):
            inp.push("k/a", _packet(seq))
        beats = 0

        async def heartbeat() -> None:
            nonlocal beats
            while True:
                beats += 1
                await asyncio.sleep(0)

        task = asyncio.ensure_future(heartbeat())
        await asyncio.sleep(0)
        start = beats
        for _ in range(30):
            await inp.__anext__()
            time.sleep(YIELD_EVERY_S)  # the consumer's work, holding the loop as a tracker update does
        task.cancel()
        assert beats - start >= 29  # each sample came after the work, so each gave the loop back

    asyncio.run(main())
