"""The process runtime every ETAM service shares: zenoh session, typed I/O, Stats, commands, shutdown.

A service subclasses `Service`, sets `kind`, and writes `async def main()`. The base opens the zenoh
session, declares the liveliness token ``.../alive``, answers Commands on ``.../cmd``, publishes Stats
on ``.../stats`` every second, and on SIGINT/SIGTERM cancels `main`, undeclares everything and closes
the session (DESIGN.md sections 3, 4 and 6).

Subscriptions follow DESIGN.md section 6: zenoh's threads only append the raw payload to a bounded
buffer and wake the asyncio loop; decoding happens on the loop, where a malformed payload is logged,
counted and skipped.
"""

from __future__ import annotations

import asyncio
import collections
import inspect
import logging
import os
import signal
import socket
import threading
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, TypeVar

import psutil
import zenoh

from services import keys
from services.config import ZenohSettings
from services.messages import CameraInfo, Command, Message, MessageError, Reply, Stats, decode
from services.stats import KeyCounter
from services.threads import one_thread

log = logging.getLogger(__name__)

Policy = Literal["latest", "fifo", "lossless"]
M = TypeVar("M", bound=Message)
SHUTDOWN_S = 2.0
YIELD_EVERY_S = 0.005  # an input always ready gives the loop back this often


class Output:
    """A typed publisher on one key; numbers messages and counts them for Stats."""

    def __init__(self, publisher: zenoh.Publisher, counter: KeyCounter) -> None:
        self._publisher = publisher
        self._counter = counter
        self._seq = 0

    @property
    def key(self) -> str:
        return self._counter.key

    @property
    def counter(self) -> KeyCounter:
        """What this publisher sent (messages, events)."""
        return self._counter

    def publish_raw(self, payload: bytes) -> None:
        """Send an already encoded payload unchanged (replay: the bytes as recorded)."""
        self._publisher.put(payload)
        self._counter.count(0)

    @property
    def matched(self) -> bool:
        """Whether any subscriber anywhere listens to this key now."""
        return bool(self._publisher.matching_status.matching)

    def publish(self, msg: Message) -> None:
        """Stamp `seq` and `sent`, encode and send."""
        self._seq += 1
        msg.seq = self._seq
        msg.sent = time.time_ns()
        self._publisher.put(msg.encode())
        self._counter.count(msg.event_count())


class Input:
    """A subscription whose samples are iterated as ``(key, message)`` on the asyncio loop.

    Policies: ``latest`` keeps only the newest sample of each key (a view of several cameras keeps
    one per camera), ``fifo`` keeps `maxsize` and drops the oldest,
    ``lossless`` makes zenoh's thread wait for room (so a reliable, blocking publisher slows down
    instead of losing data). Every drop is counted.
    """

    def __init__(
        self,
        loop: asyncio.AbstractEventLoop,
        keyexpr: str,
        expect: type[Message] | None,
        policy: Policy,
        maxsize: int,
        counter: KeyCounter,
    ) -> None:
        if policy not in ("latest", "fifo", "lossless"):
            raise ValueError(f"policy: {policy!r} is not one of latest, fifo, lossless")
        self.keyexpr = keyexpr
        self.policy = policy
        self._loop = loop
        self._expect = expect
        self._maxsize = max(1, maxsize)
        self._counter = counter
        self._buf: collections.deque[tuple[str, bytes]] = collections.deque()
        self._latest: dict[str, bytes] = {}  # the `latest` policy's buffer, oldest key first
        self._lock = threading.Lock()
        self._room = threading.Condition(self._lock)
        self._waiter: asyncio.Future[None] | None = None
        self._closed = False
        self.subscriber: zenoh.Subscriber | None = None
        self._malformed_logged = 0.0
        self._yielded = time.monotonic()  # when this input last gave the loop back

    # zenoh thread -----------------------------------------------------------------------------
    def on_sample(self, sample: zenoh.Sample) -> None:
        self.push(str(sample.key_expr), sample.payload.to_bytes())

    def push(self, key: str, payload: bytes) -> None:
        """Queue one payload by the policy (any thread); wakes the loop if it waits."""
        with self._lock:
            if self.policy == "latest":
                if self._latest.pop(key, None) is not None:
                    self._counter.skipped += 1  # superseded by design, not lost
                self._latest[key] = payload
            else:
                if self.policy == "lossless":
                    while len(self._buf) >= self._maxsize and not self._closed:
                        self._room.wait(0.1)
                elif len(self._buf) >= self._maxsize:
                    self._buf.popleft()
                    self._counter.overflow += 1
                self._buf.append((key, payload))
            waiter, self._waiter = self._waiter, None
        if waiter is not None:
            self._loop.call_soon_threadsafe(_wake, waiter)

    # asyncio side -----------------------------------------------------------------------------
    def __aiter__(self) -> Input:
        return self

    async def raw(self) -> tuple[str, bytes]:
        """The next sample undecoded: ``(key, payload)`` exactly as it arrived (for recorders)."""
        key, payload = await self._next_raw()
        self._counter.count(0)
        return key, payload

    async def __anext__(self) -> tuple[str, Message]:
        while True:
            key, payload = await self._next_raw()
            try:
                msg = decode(payload, self._expect)
            except MessageError as exc:
                self._counter.malformed += 1
                now = time.monotonic()
                if now - self._malformed_logged > 5.0:  # rate-limited: garbage can arrive at kHz
                    log.warning("malformed message on %s: %s", key, exc)
                    self._malformed_logged = now
                continue
            self._counter.sequence(key, msg.seq)
            self._counter.count(msg.event_count(), (time.time_ns() - msg.sent) / 1e6 if msg.sent else None)
            return key, msg

    async def _next_raw(self) -> tuple[str, bytes]:
        while True:
            if time.monotonic() - self._yielded >= YIELD_EVERY_S:
                # a consumer behind its input finds a sample ready every time and would never give the loop
                # back: its service's Stats, queries and other inputs would starve (the launcher then takes
                # it for hung and kills it)
                await asyncio.sleep(0)
                self._yielded = time.monotonic()
            with self._lock:
                if self._latest:
                    key = next(iter(self._latest))
                    return key, self._latest.pop(key)
                if self._buf:
                    item = self._buf.popleft()
                    if self.policy == "lossless":
                        self._room.notify()
                    return item
                if self._closed:
                    raise StopAsyncIteration
                self._waiter = self._loop.create_future()
                waiter = self._waiter
            await waiter
            self._yielded = time.monotonic()

    @property
    def counter(self) -> KeyCounter:
        """This subscription's counts (messages, drops, malformed, latency)."""
        return self._counter

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._room.notify_all()
            waiter, self._waiter = self._waiter, None
        if waiter is not None:
            self._loop.call_soon_threadsafe(_wake, waiter)


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


@dataclass
class ServiceOptions:
    """What every service process is told on its command line."""

    rig: str
    name: str
    zenoh: ZenohSettings
    stats_period_s: float = 1.0


class Service:
    """Base of every ETAM service process (see the module docstring)."""

    kind: ClassVar[str] = "service"

    def __init__(self, options: ServiceOptions) -> None:
        self.options = options
        self.rig = options.rig
        self.name = options.name
        self.session: zenoh.Session | None = None
        self.params: dict[str, Any] = {}  # settable with the `set` command
        self.status: dict[str, Any] = {}  # read-only facts answered to `ping` (e.g. the web port)
        self.paused = False
        self._counters: list[KeyCounter] = []
        self._inputs: list[Input] = []
        self._declared: list[Any] = []
        self._answering: set[asyncio.Task] = set()  # queries whose handler's work is still going on
        self._stop: asyncio.Event | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._started = time.monotonic()
        self._process = psutil.Process()

    # ------------------------------------------------------------------------------------ API --
    def key(self, topic: str) -> str:
        """This instance's key for `topic`, e.g. ``etam/<rig>/tracker/objects/tracks``."""
        return keys.key(self.rig, self.kind, self.name, topic)

    def _full_key(self, topic_or_key: str) -> str:
        return topic_or_key if topic_or_key.startswith(keys.ROOT + "/") else self.key(topic_or_key)

    def publisher(self, topic_or_key: str, *, block: bool = False, express: bool = False) -> Output:
        """A typed publisher on this service's `topic` (or on a full key starting with ``etam/``).

        Args:
            block: congestion control BLOCK (wait for slow reliable subscribers) instead of DROP.
            express: send at once without batching (small, latency-critical messages).
        """
        keyexpr = self._full_key(topic_or_key)
        congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        pub = self._session().declare_publisher(keyexpr, congestion_control=congestion, express=express)
        self._declared.append(pub)
        counter = self._counter(keyexpr, "out")
        return Output(pub, counter)

    def subscribe(
        self,
        keyexpr: str,
        expect: type[Message] | None = None,
        *,
        policy: Policy = "fifo",
        maxsize: int = 64,
    ) -> Input:
        """Subscribe to `keyexpr` (wildcards allowed); iterate the result for ``(key, message)``."""
        assert self._loop is not None, "subscribe from inside main()"
        inp = Input(self._loop, keyexpr, expect, policy, maxsize, self._counter(keyexpr, "in"))
        inp.subscriber = self._session().declare_subscriber(keyexpr, inp.on_sample)
        self._inputs.append(inp)
        return inp

    def unsubscribe(self, inp: Input) -> None:
        """End a subscription made with `subscribe` (its iteration stops); its counts leave the Stats."""
        inp.close()
        if inp.subscriber is not None:
            inp.subscriber.undeclare()
            inp.subscriber = None
        self._inputs.remove(inp)
        self._counters.remove(inp.counter)

    async def query(self, keyexpr: str, expect: type[Message], timeout_s: float = 2.0,
                    request: Message | None = None) -> list[tuple[str, Message]]:
        """Ask every queryable on `keyexpr` (off the loop), with `request` as the payload (a Command);
        the replies that decode, with their keys."""
        payload = request.encode() if request is not None else None

        def ask() -> list[tuple[str, Message]]:
            out = []
            for reply in self._session().get(keyexpr, payload=payload, timeout=timeout_s):
                if reply.ok is None:
                    continue
                try:
                    out.append((str(reply.ok.key_expr), decode(reply.ok.payload.to_bytes(), expect)))
                except MessageError as exc:
                    log.warning("ignoring a reply on %s: %s", reply.ok.key_expr, exc)
            return out

        return await asyncio.get_running_loop().run_in_executor(None, ask)

    def serve(self, topic_or_key: str, handler: Callable[[Message | None], Message | Awaitable[Message]]) -> None:
        """Answer queries on `topic` with ``handler(decoded query payload or None)``, run on the loop; a
        handler with long work returns an awaitable instead, and the query is answered once it is done
        (the loop goes on meanwhile)."""
        keyexpr = self._full_key(topic_or_key)
        loop = self._loop
        assert loop is not None

        def failed(exc: Exception) -> Reply:  # a bad request must not kill the service
            log.error("query on %s failed", keyexpr, exc_info=exc)
            return Reply(ok=False, error=f"{type(exc).__name__}: {exc}")

        def send(query: zenoh.Query, reply: Message) -> None:
            try:
                query.reply(query.key_expr, reply.encode())
            finally:
                query.drop()

        async def later(query: zenoh.Query, pending: Awaitable[Message]) -> None:
            try:
                reply = await pending
            except Exception as exc:
                reply = failed(exc)
            send(query, reply)

        def answer(query: zenoh.Query) -> None:
            try:
                request = decode(query.payload.to_bytes()) if query.payload is not None else None
            except MessageError as exc:
                send(query, Reply(ok=False, error=str(exc)))
                return

            def run() -> None:
                try:
                    reply = handler(request)
                except Exception as exc:
                    reply = failed(exc)
                if inspect.isawaitable(reply):
                    task = loop.create_task(later(query, reply))
                    self._answering.add(task)  # held until done (the loop keeps only weak references)
                    task.add_done_callback(self._answering.discard)
                else:
                    send(query, reply)

            loop.call_soon_threadsafe(run)

        self._declared.append(self._session().declare_queryable(keyexpr, answer))

    async def follow_cameras(self, cam: str, known: dict[str, CameraInfo], missing: Callable[[], bool]) -> None:
        """Keeps `known` (camera name -> its CameraInfo: size, K, pose in the rig) up to date from the rig's
        cameras matching `cam`, and asks for it (every camera answers) four times a second while `missing()`."""
        infos = keys.key(self.rig, "camera", cam, "info")
        updates = self.subscribe(infos, CameraInfo, policy="latest")

        def keep(key: str, msg: Message) -> None:
            parsed = keys.parse(key)
            if isinstance(msg, CameraInfo) and parsed:
                known[parsed[2]] = msg

        async def ask() -> None:
            while True:
                if missing():
                    for key, msg in await self.query(infos, CameraInfo, timeout_s=0.5):
                        keep(key, msg)
                await asyncio.sleep(0.25)

        asker = asyncio.ensure_future(ask())
        try:
            async for key, msg in updates:
                keep(key, msg)
        finally:
            asker.cancel()

    # ------------------------------------------------------------------------ to override --
    async def main(self) -> None:
        """The service's work; runs until it returns or the service is stopped."""
        raise NotImplementedError

    def on_command(self, cmd: Command) -> Reply | Awaitable[Reply] | None:
        """Service-specific commands (an awaitable Reply for long work); None for ops the base handles."""
        return None

    # ---------------------------------------------------------------------------- runtime --
    def run(self) -> int:
        """Run the service until it ends or is signalled; the process exit code. Its thread pools are
        held to one thread (see `services.threads`)."""
        with one_thread():
            return asyncio.run(self._run())

    async def _run(self) -> int:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._loop.add_signal_handler(sig, self._stop.set)
        conf = self.options.zenoh.zenoh_config()
        self.session = zenoh.open(conf)
        code = 0
        try:
            self._declared.append(self.session.liveliness().declare_token(self.key("alive")))
            self._stats_out = self.publisher("stats")
            self.serve("cmd", self._command)
            log.info("%s/%s up on rig %s", self.kind, self.name, self.rig)
            main = asyncio.create_task(self.main(), name="main")
            stats = asyncio.create_task(self._stats_loop(), name="stats")
            stop = asyncio.create_task(self._stop.wait(), name="stop")
            done, _ = await asyncio.wait({main, stop}, return_when=asyncio.FIRST_COMPLETED)
            if main in done and main.exception() is not None:
                log.error("%s/%s failed: %r", self.kind, self.name, main.exception(), exc_info=main.exception())
                code = 1
            for task in (main, stats, stop):
                task.cancel()
            await asyncio.gather(main, stats, stop, return_exceptions=True)
        finally:
            await asyncio.wait_for(asyncio.to_thread(self._close), SHUTDOWN_S)
        log.info("%s/%s stopped", self.kind, self.name)
        return code

    def _close(self) -> None:
        for inp in self._inputs:
            inp.close()
            if inp.subscriber is not None:
                inp.subscriber.undeclare()
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        if self.session is not None:
            self.session.close()

    def _session(self) -> zenoh.Session:
        if self.session is None:
            raise RuntimeError("the zenoh session is not open yet")
        return self.session

    def _counter(self, keyexpr: str, direction: str) -> KeyCounter:
        counter = KeyCounter(keyexpr, direction)
        self._counters.append(counter)
        return counter

    def stats(self) -> Stats:
        """This process's Stats now (also starts new rate windows)."""
        mem = self._process.memory_info()
        return Stats(
            stamp=0,
            service=self.kind,
            name=self.name,
            pid=os.getpid(),
            host=socket.gethostname(),
            uptime_s=time.monotonic() - self._started,
            cpu_percent=self._process.cpu_percent(None),
            rss_bytes=int(mem.rss),
            keys=[c.snapshot() for c in self._counters if c is not self._stats_out.counter],
        )

    async def _stats_loop(self) -> None:
        self._process.cpu_percent(None)
        while True:
            await asyncio.sleep(self.options.stats_period_s)
            self._stats_out.publish(self.stats())

    def _command(self, request: Message | None) -> Reply | Awaitable[Reply]:
        if not isinstance(request, Command):
            return Reply(ok=False, error="cmd: expected a Command message")
        custom = self.on_command(request)
        if custom is not None:
            return custom
        args = request.args or {}
        if request.op == "ping":
            return Reply(ok=True, result={"service": self.kind, "name": self.name, "pid": os.getpid(), **self.status})
        if request.op in ("pause", "resume"):
            self.paused = request.op == "pause"
            return Reply(ok=True)
        if request.op == "get":
            return Reply(ok=True, result=dict(self.params))
        if request.op == "set":
            unknown = [k for k in args if k not in self.params]
            if unknown:
                return Reply(ok=False, error=f"set: unknown parameter(s) {', '.join(unknown)}")
            for k, v in args.items():
                if not isinstance(v, type(self.params[k])) and not (
                    isinstance(self.params[k], float) and isinstance(v, int)
                ):
                    return Reply(ok=False, error=f"set: {k} must be {type(self.params[k]).__name__}")
            self.params.update(args)
            return Reply(ok=True, result=dict(self.params))
        return Reply(ok=False, error=f"cmd: unknown op {request.op!r}")
