"""Every message round-trips through msgpack unchanged; garbage only ever raises MessageError."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from services import messages as m
from services.messages import EVENT_DTYPE, MESSAGE_TYPES, MessageError, decode

ints = st.integers(-(2**62), 2**62)
n_items = st.integers(0, 40)


@st.composite
def event_arrays(draw, n=n_items):  # noqa: ANN001, ANN201
    count = draw(n)
    ev = np.zeros(count, EVENT_DTYPE)
    ev["t"] = np.sort(draw(hnp.arrays(np.int64, count, elements=st.integers(0, 2**40))))
    ev["x"] = draw(hnp.arrays(np.uint16, count))
    ev["y"] = draw(hnp.arrays(np.uint16, count))
    ev["p"] = draw(hnp.arrays(np.uint8, count, elements=st.integers(0, 1)))
    return ev


def header():  # noqa: ANN201
    return {"seq": st.integers(0, 2**40), "stamp": ints, "sent": st.integers(1, 2**62)}


floats = st.floats(allow_nan=False, width=64)
f32 = st.floats(allow_nan=False, width=32)


@st.composite
def tracks(draw):  # noqa: ANN001, ANN201
    n = draw(n_items)
    with_xyz = draw(st.booleans())
    return m.Tracks(
        **{k: draw(v) for k, v in header().items()}, t=draw(ints),
        id=draw(hnp.arrays("<i4", n)), box=draw(hnp.arrays("<f4", (n, 4), elements=f32)),
        score=draw(hnp.arrays("<f4", n, elements=f32)), vel=draw(hnp.arrays("<f4", (n, 2), elements=f32)),
        state=draw(hnp.arrays("|u1", n, elements=st.integers(0, 2))),
        xyz=draw(hnp.arrays("<f4", (n, 3), elements=f32)) if with_xyz else None,
    )


MESSAGES = st.one_of(
    st.builds(m.EventPacket, **header(), width=st.integers(1, 4096), height=st.integers(1, 4096),
              events=event_arrays()),
    st.builds(m.CameraInfo, **header(), width=st.integers(1, 4096), height=st.integers(1, 4096),
              K=hnp.arrays("<f8", (3, 3), elements=floats), dist_model=st.sampled_from(["none", "radtan"]),
              dist=st.none() | hnp.arrays("<f8", 5, elements=floats)),
    n_items.flatmap(lambda n: st.builds(
        m.ImuPacket, **header(), t=hnp.arrays("<i8", n), gyro=hnp.arrays("<f8", (n, 3), elements=floats),
        accel=hnp.arrays("<f8", (n, 3), elements=floats))),
    st.builds(m.Pose, **header(), t=ints, p=hnp.arrays("<f8", 3, elements=floats),
              q=hnp.arrays("<f8", 4, elements=floats), omega=st.none() | hnp.arrays("<f8", 3, elements=floats)),
    tracks(),
    n_items.flatmap(lambda n: st.builds(
        m.PointCloud, **header(), t=ints, points=hnp.arrays("<f4", (n, 3), elements=f32),
        colors=st.none() | hnp.arrays("|u1", (n, 3)))),
    st.builds(m.Image, **header(), t=ints, encoding=st.sampled_from(m.Image.ENCODINGS),
              width=st.integers(0, 5000), height=st.integers(0, 5000), data=st.binary(max_size=200)),
    st.builds(m.Stats, **header(), service=st.text(max_size=10), name=st.text(max_size=10),
              cpu_percent=floats, keys=st.lists(st.fixed_dictionaries(
                  {k: st.integers(0, 100) for k in m.Stats.ROW_FIELDS}), max_size=3)),
    st.builds(m.Command, **header(), op=st.text(max_size=10),
              args=st.none() | st.dictionaries(st.text(max_size=5), ints | st.text(max_size=5), max_size=3)),
    st.builds(m.Reply, **header(), ok=st.booleans(), error=st.text(max_size=20)),
)


def _same(a, b) -> bool:  # noqa: ANN001
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    return a == b


@given(MESSAGES)
@settings(max_examples=300, deadline=None)
def test_every_message_round_trips(msg: m.Message) -> None:
    back = decode(msg.encode())
    assert type(back) is type(msg)
    for f in dataclasses.fields(msg):
        assert _same(getattr(msg, f.name), getattr(back, f.name)), f.name


def test_all_design_messages_exist() -> None:
    assert set(MESSAGE_TYPES) == {"EventPacket", "CameraInfo", "ImuPacket", "Pose", "Tracks", "PointCloud",
                                  "Image", "Stats", "Command", "Reply"}


def test_arrays_decode_without_copy() -> None:
    ev = np.zeros(1000, EVENT_DTYPE)
    ev["t"] = np.arange(1000)
    payload = m.EventPacket(width=346, height=260, events=ev).encode()
    back = decode(payload)
    assert back.events.base is not None and not back.events.flags.owndata  # a view on the payload bytes
    assert not back.events.flags.writeable
    assert np.array_equal(back.events["t"], ev["t"])


@given(st.binary(max_size=300))
@settings(max_examples=500, deadline=None)
def test_garbage_bytes_raise_message_error_only(data: bytes) -> None:
    try:
        decode(data)
    except MessageError:
        pass


_mp_values = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8)
    | st.binary(max_size=32),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


@given(st.sampled_from(sorted(MESSAGE_TYPES)), st.dictionaries(
    st.sampled_from(["v", "seq", "stamp", "sent", "width", "height", "events", "t", "id", "box", "score", "vel",
                     "state", "K", "p", "q", "points", "data", "encoding", "keys", "service", "name", "op", "ok",
                     "gyro", "accel", "args"]), _mp_values, max_size=10))
@settings(max_examples=500, deadline=None)
def test_well_formed_msgpack_with_wrong_fields_raises_message_error(kind: str, body: dict) -> None:
    try:
        decode(msgpack.packb({"type": kind, **body}, use_bin_type=True))
    except MessageError:
        pass


def _events_packet(**override) -> bytes:  # noqa: ANN003
    body = msgpack.unpackb(m.EventPacket(width=4, height=4, events=np.zeros(3, EVENT_DTYPE)).encode())
    body.update(override)
    return msgpack.packb(body, use_bin_type=True)


@pytest.mark.parametrize(("payload", "field"), [
    (b"\xc1", "payload"),
    (msgpack.packb([1, 2]), "payload"),
    (msgpack.packb({"type": "Nope", "v": 1}), "type"),
    (_events_packet(v=99), "EventPacket.v"),
    (_events_packet(width="wide"), "EventPacket.width"),
    (_events_packet(events={"dtype": "<f4", "shape": [3], "data": b"\0" * 12}), "EventPacket.events"),
    (_events_packet(events={"dtype": "|O8", "shape": [1], "data": b"\0" * 8}), "EventPacket.events"),
    (_events_packet(events={"dtype": [["t", "<i8"]], "shape": [2], "data": b"\0" * 3}), "EventPacket.events"),
    (_events_packet(height=0), "EventPacket.width/height"),
])
def test_malformed_payload_names_the_field(payload: bytes, field: str) -> None:
    with pytest.raises(MessageError, match=field.replace(".", r"\.").replace("/", "/")):
        decode(payload)


def test_missing_field_and_inconsistent_lengths_are_named() -> None:
    body = msgpack.unpackb(m.Tracks.from_boxes(5, [1, 2], [[0, 0, 1, 1], [1, 1, 2, 2]]).encode())
    del body["box"]
    with pytest.raises(MessageError, match=r"Tracks\.box: missing"):
        decode(msgpack.packb(body, use_bin_type=True))
    bad = m.Tracks.from_boxes(5, [1, 2], [[0, 0, 1, 1], [1, 1, 2, 2]])
    bad.score = np.ones(3, "<f4")
    with pytest.raises(MessageError, match="differ in length"):
        decode(bad.encode())


def test_values_that_cannot_travel_raise_message_error_on_encode() -> None:
    with pytest.raises(MessageError, match="Command: cannot encode"):
        m.Command(op="set", args={"big": 2**70}).encode()
    with pytest.raises(MessageError, match="Command: cannot encode"):
        m.Command(op="set", args={"obj": object()}).encode()


def test_expect_rejects_other_types() -> None:
    with pytest.raises(MessageError, match="expected EventPacket"):
        decode(m.Command(op="ping").encode(), m.EventPacket)


def test_image_helpers_round_trip() -> None:
    img = (np.arange(48 * 64) % 251).astype(np.uint8).reshape(48, 64)
    for enc in ("png", "raw8"):
        back = m.image_to_array(decode(m.image_from_array(7, img, enc).encode()))
        assert np.array_equal(back, img)
    with pytest.raises(MessageError, match="Image.data"):
        m.image_to_array(m.Image(t=0, encoding="jpeg", width=2, height=2, data=b"not a jpeg"))


def test_spliced_encoding_is_byte_for_byte_msgpack() -> None:
    import dataclasses

    from services.messages import _pack_default

    for n in (0, 3, 300, 30_000):  # bin 8, 16 and 32 headers
        msg = m.EventPacket(seq=2, stamp=9, sent=5, width=4, height=4, events=np.zeros(n, EVENT_DTYPE))
        body = {"type": "EventPacket", "v": 1, **{f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}}
        assert msg.encode() == msgpack.packb(body, default=_pack_default, use_bin_type=True)


def test_malloc_tuning_applies_on_glibc() -> None:
    import platform

    from services.config import tune_malloc

    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        pytest.skip("mallopt is glibc's")
    assert tune_malloc()


def test_json_view_summarises_long_arrays_unless_asked_for_all() -> None:
    n = 4  # 12 coordinates: over the 8 shown in a summary
    msg = m.Tracks(seq=1, stamp=2, t=3, id=np.arange(n, dtype="<i4"), box=np.ones((n, 4), "<f4"),
                   score=np.ones(n, "<f4"), vel=np.zeros((n, 2), "<f4"), state=np.ones(n, "|u1"),
                   xyz=np.arange(3 * n, dtype="<f4").reshape(n, 3))
    short = msg.to_dict()
    assert short["id"] == [0, 1, 2, 3] and short["xyz"]["shape"] == [4, 3] and len(short["xyz"]["head"]) == 8
    full = msg.to_dict(full=True)
    assert full["xyz"] == msg.xyz.tolist() and full["box"] == msg.box.tolist()
    ev = np.zeros(20, EVENT_DTYPE)
    ev["x"] = np.arange(20)
    packet = m.EventPacket(seq=1, stamp=2, width=64, height=48, events=ev)
    assert packet.to_dict()["events"]["len"] == 20 and len(packet.to_dict()["events"]["head"]["x"]) == 8
    assert packet.to_dict(full=True)["events"]["x"] == list(range(20))
