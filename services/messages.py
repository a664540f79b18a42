"""Every ETAM wire message, one typed class each, with its msgpack encoding (DESIGN.md section 4).

This module is the single source of truth for both ends of the wire. A message is a keyword-only
dataclass; its fields carry a `Spec` in their metadata that says how the field is checked and
encoded. Arrays travel as msgpack maps ``{"dtype", "shape", "data": bin}`` of little-endian data and
are decoded with ``np.frombuffer`` (no copy, read-only views). Anything malformed raises
`MessageError`, naming the message type and field.
"""

from __future__ import annotations

import dataclasses
import math
import functools
import re
import threading
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import msgpack
import numpy as np

EVENT_DTYPE = np.dtype([("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
"""One event: time in microseconds, pixel column and row, polarity (1 = ON)."""

_SIMPLE_DTYPE = re.compile(r"^[<|][iufb][1248]$")
_MAX_NDIM = 4


class MessageError(ValueError):
    """A payload that cannot be decoded into a valid message; the text names the field at fault."""


# ---------------------------------------------------------------------------------------------
# Field specifications


@dataclass(frozen=True)
class Spec:
    """How one field is checked on decode. `kind` is one of int, float, str, bool, map, rows, array."""

    kind: str
    optional: bool = False
    dtype: np.dtype | None = None  # arrays: the exact dtype required
    shape: tuple[int | None, ...] | None = None  # arrays: None entries are free dimensions


def _spec(kind: str, default: Any = dataclasses.MISSING, **kw: Any) -> Any:
    optional = default is not dataclasses.MISSING
    return field(default=default, metadata={"spec": Spec(kind, optional=optional, **kw)})


def _array(dtype: Any, shape: tuple[int | None, ...], optional: bool = False) -> Any:
    spec = Spec("array", optional=optional, dtype=np.dtype(dtype), shape=shape)
    return field(default=None if optional else dataclasses.MISSING, metadata={"spec": spec})


@functools.lru_cache(maxsize=64)
def _record_descr(dtype: np.dtype) -> list[list[str]]:
    """[[name, format], ...] of a structured dtype (numpy builds `descr` in Python: 14 us a call)."""
    return [[name, fmt] for name, fmt in dtype.descr]


def _array_parts(arr: np.ndarray) -> tuple[dict[str, Any], memoryview]:
    """The dtype/shape header and the raw little-endian bytes of an array."""
    arr = np.ascontiguousarray(arr)
    if arr.dtype.names:
        dtype: Any = _record_descr(arr.dtype)
    else:
        dtype = arr.dtype.newbyteorder("<").str if arr.dtype.byteorder == ">" else arr.dtype.str
        if arr.dtype.byteorder == ">":
            arr = arr.astype(dtype)
    return {"dtype": dtype, "shape": list(arr.shape)}, memoryview(arr.reshape(-1).view(np.uint8))


def _encode_array(arr: np.ndarray) -> dict[str, Any]:
    head, data = _array_parts(arr)
    return {**head, "data": data}


def _bin_header(n: int) -> bytes:
    if n < 1 << 8:
        return b"\xc4" + n.to_bytes(1, "big")
    if n < 1 << 16:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")


_local = threading.local()


def _pack(body: dict[str, Any]) -> bytes:
    """msgpack of `body` with its arrays' bytes spliced in: one copy per array. (`msgpack.packb`
    allocates a 1 MiB buffer on every call; on a VM its page faults made a 234 kB EventPacket cost
    150 us instead of 7.) The bytes are the same as packb's."""
    packer = getattr(_local, "packer", None)
    if packer is None:
        packer = _local.packer = msgpack.Packer(use_bin_type=True, default=_pack_default)
    parts: list[bytes | memoryview] = [packer.pack_map_header(len(body))]
    for key, value in body.items():
        parts.append(packer.pack(key))
        if isinstance(value, np.ndarray):
            head, data = _array_parts(value)
            parts += [packer.pack_map_header(3), packer.pack("dtype"), packer.pack(head["dtype"]),
                      packer.pack("shape"), packer.pack(head["shape"]), packer.pack("data"),
                      _bin_header(len(data)), data]
        else:
            parts.append(packer.pack(value))
    return b"".join(parts)


_DTYPES: dict[Any, np.dtype] = {}  # dtypes already parsed, by their wire form (a few kinds ever travel)


def _parse_dtype(raw: Any, where: str) -> np.dtype:
    key = raw if isinstance(raw, str) else None
    if isinstance(raw, (list, tuple)) and all(isinstance(item, (list, tuple)) for item in raw):
        key = tuple(tuple(item) for item in raw)
    try:
        known = _DTYPES.get(key) if key is not None else None
    except TypeError:  # unhashable entries: let the checks below name them
        key, known = None, None
    if known is not None:
        return known
    dtype = _check_dtype(raw, where)
    if key is not None and len(_DTYPES) < 256:
        _DTYPES[key] = dtype
    return dtype


def _check_dtype(raw: Any, where: str) -> np.dtype:
    if isinstance(raw, str) and _SIMPLE_DTYPE.match(raw):
        return np.dtype(raw)
    if isinstance(raw, (list, tuple)) and 0 < len(raw) <= 16:
        parts = []
        for item in raw:
            ok = isinstance(item, (list, tuple)) and len(item) == 2
            if not (ok and isinstance(item[0], str) and isinstance(item[1], str) and _SIMPLE_DTYPE.match(item[1])):
                raise MessageError(f"{where}: bad structured dtype entry {item!r}")
            parts.append((item[0], item[1]))
        try:
            return np.dtype(parts)
        except (TypeError, ValueError) as exc:
            raise MessageError(f"{where}: bad dtype {raw!r}: {exc}") from None
    raise MessageError(f"{where}: unsupported dtype {raw!r}")


def _decode_array(raw: Any, spec: Spec, where: str) -> np.ndarray:
    if not isinstance(raw, dict) or set(raw) != {"dtype", "shape", "data"}:
        raise MessageError(f"{where}: expected an array map with dtype, shape, data")
    dtype = _parse_dtype(raw["dtype"], where)
    shape = raw["shape"]
    if not isinstance(shape, (list, tuple)) or len(shape) > _MAX_NDIM:
        raise MessageError(f"{where}: bad shape {shape!r}")
    if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape):
        raise MessageError(f"{where}: bad shape {shape!r}")
    data = raw["data"]
    if not isinstance(data, (bytes, bytearray)):
        raise MessageError(f"{where}: data is not binary")
    count = math.prod(shape)
    if count * dtype.itemsize != len(data):
        raise MessageError(f"{where}: {len(data)} bytes do not hold shape {shape} of {dtype}")
    if spec.dtype is not None and dtype != spec.dtype:
        raise MessageError(f"{where}: dtype {dtype} where {spec.dtype} is required")
    _check_shape(tuple(shape), spec, where)
    return np.frombuffer(data, dtype=dtype, count=count).reshape(shape)


def _check_shape(shape: tuple[int, ...], spec: Spec, where: str) -> None:
    if spec.shape is None:
        return
    if len(shape) != len(spec.shape) or any(w is not None and w != n for w, n in zip(spec.shape, shape, strict=True)):
        want = tuple("N" if w is None else w for w in spec.shape)
        raise MessageError(f"{where}: shape {shape} where {want} is required")


def _check_scalar(value: Any, spec: Spec, where: str) -> Any:
    kind = spec.kind
    if kind == "int" and isinstance(value, int) and not isinstance(value, bool):
        return value
    if kind == "float" and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if kind == "str" and isinstance(value, str):
        return value
    if kind == "bool" and isinstance(value, bool):
        return value
    if kind == "map" and isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return value
    if kind == "rows" and isinstance(value, list) and all(isinstance(r, dict) for r in value):
        return value
    raise MessageError(f"{where}: expected {kind}, got {type(value).__name__}")


def _pack_default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return _encode_array(obj)
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"cannot encode {type(obj).__name__}")


# ---------------------------------------------------------------------------------------------
# Messages


@dataclass(kw_only=True)
class Message:
    """Header common to all messages: per-publisher `seq`, sensor `stamp` (us), wall-clock `sent` (ns)."""

    TYPE: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1
    EVENTS: ClassVar[str | None] = None  # name of the field whose length counts as "events" in Stats

    seq: int = _spec("int", 0)
    stamp: int = _spec("int", 0)
    sent: int = _spec("int", 0)

    def encode(self) -> bytes:
        """msgpack bytes of this message (`sent` set to the wall clock if 0); MessageError if a value
        cannot travel (an integer beyond 64 bits, an arbitrary object)."""
        body: dict[str, Any] = {"type": self.TYPE, "v": self.VERSION}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            body[f.name] = value
        if not body["sent"]:
            body["sent"] = time.time_ns()
        try:
            return _pack(body)
        except (TypeError, ValueError, OverflowError) as exc:
            raise MessageError(f"{self.TYPE}: cannot encode ({exc})") from None

    def event_count(self) -> int:
        """Events carried (EventPacket) or items (Tracks, PointCloud); 0 for other messages."""
        if self.EVENTS is None:
            return 0
        value = getattr(self, self.EVENTS)
        return 0 if value is None else len(value)

    def check(self) -> None:
        """Cross-field consistency, raising MessageError; overridden where fields relate."""

    def to_dict(self, full: bool = False) -> dict[str, Any]:
        """A JSON-friendly view: arrays up to 8 items (all of them when `full`) shown as lists, longer
        ones summarised so that an event packet stays one readable line."""
        out: dict[str, Any] = {"type": self.TYPE, "v": self.VERSION}
        for f in dataclasses.fields(self):
            out[f.name] = _summarise(getattr(self, f.name), full)
        return out


def _summarise(value: Any, full: bool = False) -> Any:
    if isinstance(value, np.ndarray):
        if value.dtype.names:
            if full:
                return {n: value[n].tolist() for n in value.dtype.names}
            head = {n: value[n][:8].tolist() for n in value.dtype.names}
            return {"len": len(value), "head": head}
        if full or value.size <= 8:
            return value.tolist()
        return {"shape": list(value.shape), "dtype": value.dtype.str, "head": value.reshape(-1)[:8].tolist()}
    if isinstance(value, (bytes, bytearray, memoryview)):
        return f"<{len(value)} bytes>"
    return value


def _same_length(msg: Message, names: tuple[str, ...]) -> None:
    lengths = {n: len(getattr(msg, n)) for n in names if getattr(msg, n) is not None}
    if len(set(lengths.values())) > 1:
        raise MessageError(f"{msg.TYPE}: arrays differ in length: {lengths}")


@dataclass(kw_only=True)
class EventPacket(Message):
    """A time slice of events from one camera, sorted by t; `stamp` is the end of the window (us)."""

    TYPE: ClassVar[str] = "EventPacket"
    EVENTS: ClassVar[str | None] = "events"
    width: int = _spec("int")
    height: int = _spec("int")
    events: np.ndarray = _array(EVENT_DTYPE, (None,))

    def check(self) -> None:
        if not (0 < self.width <= 65535 and 0 < self.height <= 65535):
            raise MessageError(f"EventPacket.width/height: bad sensor size {self.width}x{self.height}")


@dataclass(kw_only=True)
class CameraInfo(Message):
    """Sensor size and calibration; `dist_model` is radtan (k1 k2 p1 p2 k3), equidistant or none."""

    TYPE: ClassVar[str] = "CameraInfo"
    width: int = _spec("int")
    height: int = _spec("int")
    K: np.ndarray = _array("<f8", (3, 3))
    dist_model: str = _spec("str", "none")
    dist: np.ndarray | None = _array("<f8", (None,), optional=True)
    T_body_cam: np.ndarray | None = _array("<f8", (4, 4), optional=True)
    source: str = _spec("str", "")


@dataclass(kw_only=True)
class ImuPacket(Message):
    """Inertial samples in the camera frame: times (us), gyro (rad/s), accel (m/s^2)."""

    TYPE: ClassVar[str] = "ImuPacket"
    EVENTS: ClassVar[str | None] = "t"
    t: np.ndarray = _array("<i8", (None,))
    gyro: np.ndarray = _array("<f8", (None, 3))
    accel: np.ndarray = _array("<f8", (None, 3))

    def check(self) -> None:
        _same_length(self, ("t", "gyro", "accel"))


@dataclass(kw_only=True)
class Pose(Message):
    """T_world_cam at time t (us): position p (m) and quaternion q (x, y, z, w)."""

    TYPE: ClassVar[str] = "Pose"
    t: int = _spec("int")
    p: np.ndarray = _array("<f8", (3,))
    q: np.ndarray = _array("<f8", (4,))
    frame: str = _spec("str", "world")
    child: str = _spec("str", "cam0")
    cov: np.ndarray | None = _array("<f8", (6, 6), optional=True)
    omega: np.ndarray | None = _array("<f8", (3,), optional=True)


@dataclass(kw_only=True)
class Tracks(Message):
    """Tracked objects at time t (us): boxes x, y, w, h in pixels (top-left origin), velocity px/s."""

    TYPE: ClassVar[str] = "Tracks"
    EVENTS: ClassVar[str | None] = "id"
    TENTATIVE: ClassVar[int] = 0
    TRACKED: ClassVar[int] = 1
    LOST: ClassVar[int] = 2
    t: int = _spec("int")
    id: np.ndarray = _array("<i4", (None,))
    box: np.ndarray = _array("<f4", (None, 4))
    score: np.ndarray = _array("<f4", (None,))
    vel: np.ndarray = _array("<f4", (None, 2))
    state: np.ndarray = _array("|u1", (None,))
    xyz: np.ndarray | None = _array("<f4", (None, 3), optional=True)
    size_m: np.ndarray | None = _array("<f4", (None,), optional=True)

    def check(self) -> None:
        _same_length(self, ("id", "box", "score", "vel", "state", "xyz", "size_m"))

    @classmethod
    def from_boxes(cls, t_us: int, ids: Any, boxes: Any, **kw: Any) -> Tracks:
        """Tracks from ids and boxes alone (ground truth): score 1, zero velocity, state tracked."""
        n = len(ids)
        return cls(
            t=int(t_us),
            stamp=int(t_us),
            id=np.asarray(ids, "<i4"),
            box=np.asarray(boxes, "<f4").reshape(n, 4),
            score=np.ones(n, "<f4"),
            vel=np.zeros((n, 2), "<f4"),
            state=np.full(n, cls.TRACKED, "|u1"),
            **kw,
        )


@dataclass(kw_only=True)
class PointCloud(Message):
    """3D points in the world frame (m); `keyframe` is the 4x4 T_world_cam they were seen from."""

    TYPE: ClassVar[str] = "PointCloud"
    EVENTS: ClassVar[str | None] = "points"
    t: int = _spec("int")
    points: np.ndarray = _array("<f4", (None, 3))
    colors: np.ndarray | None = _array("|u1", (None, 3), optional=True)
    confidence: np.ndarray | None = _array("<f4", (None,), optional=True)
    keyframe: np.ndarray | None = _array("<f8", (4, 4), optional=True)

    def check(self) -> None:
        _same_length(self, ("points", "colors", "confidence"))


@dataclass(kw_only=True)
class Image(Message):
    """An image: `data` is jpeg/png bytes, or raw8 (uint8 HxW or HxWx3) / rawf32 pixels."""

    TYPE: ClassVar[str] = "Image"
    ENCODINGS: ClassVar[tuple[str, ...]] = ("jpeg", "png", "raw8", "rawf32")
    t: int = _spec("int")
    encoding: str = _spec("str")
    width: int = _spec("int")
    height: int = _spec("int")
    data: Any = _spec("bin")

    def check(self) -> None:
        if self.encoding not in self.ENCODINGS:
            raise MessageError(f"Image.encoding: {self.encoding!r} is not one of {self.ENCODINGS}")


@dataclass(kw_only=True)
class Stats(Message):
    """Once a second from every service: per key (`keys` rows) rates, drops, malformed, latency."""

    TYPE: ClassVar[str] = "Stats"
    service: str = _spec("str")
    name: str = _spec("str")
    pid: int = _spec("int", 0)
    host: str = _spec("str", "")
    uptime_s: float = _spec("float", 0.0)
    cpu_percent: float = _spec("float", 0.0)
    rss_bytes: int = _spec("int", 0)
    keys: list = _spec("rows", dataclasses.MISSING)
    ROW_FIELDS: ClassVar[tuple[str, ...]] = (
        "key", "dir", "messages", "events", "msg_rate", "event_rate", "dropped", "malformed",
        "latency_p50_ms", "latency_p99_ms",
    )

    def check(self) -> None:
        for i, row in enumerate(self.keys):
            missing = [k for k in self.ROW_FIELDS if k not in row]
            if missing:
                raise MessageError(f"Stats.keys[{i}]: missing {', '.join(missing)}")


@dataclass(kw_only=True)
class Command(Message):
    """A request to a service (`op`: reset, pause, resume, set, get) with its arguments."""

    TYPE: ClassVar[str] = "Command"
    op: str = _spec("str")
    args: dict = _spec("map", None)


@dataclass(kw_only=True)
class Reply(Message):
    """The answer to a Command: `ok`, and an `error` text or a `result` map."""

    TYPE: ClassVar[str] = "Reply"
    ok: bool = _spec("bool")
    error: str = _spec("str", "")
    result: dict = _spec("map", None)


MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.TYPE: cls
    for cls in (EventPacket, CameraInfo, ImuPacket, Pose, Tracks, PointCloud, Image, Stats, Command, Reply)
}


def decode(payload: bytes | bytearray | memoryview, expect: type[Message] | None = None) -> Message:
    """Decode one payload into its message class; raise MessageError naming the field at fault.

    Args:
        payload: msgpack bytes as produced by `Message.encode`.
        expect: if given, the payload must be of this type.
    """
    try:
        body = msgpack.unpackb(payload, raw=False, strict_map_key=True, max_bin_len=1 << 31)
    except Exception as exc:  # msgpack raises several unrelated types on garbage
        raise MessageError(f"payload: not msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(body, dict):
        raise MessageError(f"payload: expected a map, got {type(body).__name__}")
    kind = body.get("type")
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise MessageError(f"type: unknown message type {kind!r}")
    if expect is not None and cls is not expect:
        raise MessageError(f"type: got {kind}, expected {expect.TYPE}")
    version = body.get("v")
    if not isinstance(version, int) or version < 1:
        raise MessageError(f"{kind}.v: bad version {version!r}")
    if version > cls.VERSION:
        raise MessageError(f"{kind}.v: version {version} is newer than this ETAM reads ({cls.VERSION})")
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        spec: Spec = f.metadata["spec"]
        where = f"{kind}.{f.name}"
        raw = body.get(f.name)
        if raw is None:
            if not spec.optional:
                raise MessageError(f"{where}: missing")
            continue
        if spec.kind == "array":
            values[f.name] = _decode_array(raw, spec, where)
        elif spec.kind == "bin":
            if not isinstance(raw, (bytes, bytearray)):
                raise MessageError(f"{where}: expected binary, got {type(raw).__name__}")
            values[f.name] = raw
        else:
            values[f.name] = _check_scalar(raw, spec, where)
    msg = cls(**values)
    msg.check()
    return msg


COUNTED = ("events", "id", "points")  # the array whose length is a message's count in Stats
_PEEKED = ("type", "seq", "sent")


def peek(payload: bytes) -> dict[str, Any]:
    """`type`, `seq`, `sent` and the length (`count`) of a message's counted array, without unpacking
    (or copying) any array data: for those that see every message (launcher, recorder). Raises
    msgpack or ValueError exceptions on garbage."""
    unpacker = msgpack.Unpacker(raw=False)
    unpacker.feed(payload)
    out: dict[str, Any] = {}
    for _ in range(unpacker.read_map_header()):
        key = unpacker.unpack()
        if key in _PEEKED:
            out[key] = unpacker.unpack()
        elif key in COUNTED and "count" not in out:
            for _ in range(unpacker.read_map_header()):
                if unpacker.unpack() == "shape":
                    shape = unpacker.unpack()
                    out["count"] = shape[0] if shape else 0
                else:
                    unpacker.skip()
        else:
            unpacker.skip()
    return out


def image_from_array(t_us: int, img: np.ndarray, encoding: str = "jpeg", quality: int = 80) -> Image:
    """Compress an 8-bit image (HxW or HxWx3 BGR; png also takes 16-bit grey) into an Image message."""
    import cv2

    h, w = img.shape[:2]
    if encoding in ("jpeg", "png"):
        ext, params = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, quality]) if encoding == "jpeg" else (".png", [])
        ok, buf = cv2.imencode(ext, img, params)
        if not ok:
            raise ValueError(f"cannot encode a {img.shape} image as {encoding}")
        data = buf.tobytes()
    else:
        data = np.ascontiguousarray(img, np.float32 if encoding == "rawf32" else np.uint8).tobytes()
    return Image(t=int(t_us), stamp=int(t_us), encoding=encoding, width=w, height=h, data=data)


def image_to_array(msg: Image) -> np.ndarray:
    """Pixels of an Image message (BGR uint8 for jpeg/png); MessageError if they do not decode."""
    import cv2

    if msg.encoding in ("jpeg", "png"):
        img = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise MessageError(f"Image.data: not a valid {msg.encoding}")
        return img
    dtype = np.float32 if msg.encoding == "rawf32" else np.uint8
    pixels = np.frombuffer(msg.data, dtype)
    n = msg.width * msg.height
    if n == 0 or pixels.size not in (n, 3 * n):
        raise MessageError(f"Image.data: {pixels.size} values do not fit {msg.width}x{msg.height}")
    channels = pixels.size // n
    return pixels.reshape(msg.height, msg.width) if channels == 1 else pixels.reshape(msg.height, msg.width, 3)
