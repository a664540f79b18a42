"""The dashboard's pure parts: the map a browser is sent (chunks, merges, the cap), colours, images."""

from __future__ import annotations

import numpy as np

from services.messages import PointCloud, Tracks
from web.cloud import MAX_CHUNKS, MapLayer
from web.render import draw_tracks, event_frame, track_colour, viewable


def _cloud(n: int, z: float, seed: int = 0) -> PointCloud:
    pts = np.random.default_rng(seed).normal(0, 0.5, (n, 3)).astype(np.float32)
    pts[:, 2] += z
    return PointCloud(t=0, points=pts, keyframe=np.eye(4))


def test_map_layer_sends_chunks_once_then_merges_them_under_the_cap() -> None:
    layer = MapLayer(cap=5000)
    for i in range(MAX_CHUNKS - 1):
        assert layer.add(_cloud(100, 2.0, i)) is not None
        assert not layer.merge_due()
    assert layer.add(PointCloud(t=0, points=np.empty((0, 3), np.float32))) is None  # nothing to send
    layer.add(_cloud(100, 2.0, 99))
    assert layer.merge_due() and layer.total == MAX_CHUNKS * 100
    base = layer.merge()
    assert len(base) == MAX_CHUNKS * 100 and not layer.chunks and layer.total == len(base)
    layer.add(_cloud(20_000, 4.0))
    assert layer.merge_due()  # over the cap
    base = layer.merge()
    assert len(base) == 5000 and layer.total == 5000
    # decimation is uniform: the far, dense chunk keeps its share (20000 of 21600 points)
    assert 0.85 < np.mean(base.points[:, 2] > 3.0) < 0.99


def test_map_layer_colours_by_depth_from_the_keyframe_height_and_intensity() -> None:
    layer = MapLayer()
    near, far = _cloud(500, 1.0), _cloud(500, 5.0, 1)
    chunks = [layer.add(near), layer.add(far)]
    layer.merge()
    colours = layer.colours(layer.base, "depth")
    assert colours.shape == (1000, 3) and colours.dtype == np.uint8
    # turbo: near is blue, far is red
    assert colours[:500, 2].mean() > colours[:500, 0].mean() and colours[500:, 0].mean() > colours[500:, 2].mean()
    assert layer.colours(chunks[0], "height").shape == (500, 3)
    grey = layer.colours(chunks[0], "intensity")
    assert np.all(grey == 200)  # no published colours: uniform
    painted = PointCloud(t=0, points=near.points, colors=np.full((500, 3), 7, np.uint8))
    assert np.all(layer.colours(layer.add(painted), "intensity") == 7)


def test_map_layer_replace_with_the_whole_map_and_clear() -> None:
    layer = MapLayer(cap=1000)
    layer.add(_cloud(10, 1.0))
    layer.replace(_cloud(3000, 2.0))
    assert layer.total == 1000 and not layer.chunks
    layer.clear()
    assert layer.total == 0 and layer.base is None


def test_viewable_shows_depth_mosaics_and_colour_images() -> None:
    depth = np.full((20, 30), np.nan, np.float32)
    depth[5:15, 5:25] = np.linspace(1, 5, 20)[None, :]
    rgb = viewable(depth)
    assert rgb.shape == (20, 30, 3) and rgb.dtype == np.uint8
    assert np.all(rgb[0, 0] == 0) and rgb[10, 6].any()  # unknown black, known coloured
    mosaic = viewable(np.arange(600, dtype=np.uint16).reshape(20, 30) * 100)
    assert mosaic[0, 0, 0] == 0 and mosaic[-1, -1, 0] == 255 and np.all(mosaic[..., 0] == mosaic[..., 2])
    bgr = np.zeros((4, 4, 3), np.uint8)
    bgr[..., 0] = 255  # blue in OpenCV's order
    assert np.all(viewable(bgr)[..., 2] == 255) and np.all(viewable(bgr)[..., 0] == 0)


def test_event_image_draws_tracked_boxes_in_their_colour_and_truth_in_white() -> None:
    ev = np.zeros(4, [("t", "<i8"), ("x", "<u2"), ("y", "<u2"), ("p", "u1")])
    img = event_frame(ev, 64, 48)
    tracks = Tracks.from_boxes(0, [7], [[10, 10, 20, 10]])
    truth = Tracks.from_boxes(0, [1], [[2, 30, 8, 8]])
    out = draw_tracks(img, [tracks], [truth], scale=2)
    assert out.shape == (96, 128, 3)
    assert tuple(out[20, 30]) == track_colour(7)  # the top edge of the tracked box, upscaled
    assert tuple(out[60, 8]) == (235, 235, 235)  # the truth box's top edge
    tentative = Tracks.from_boxes(0, [7], [[10, 10, 20, 10]])
    tentative.state[:] = Tracks.TENTATIVE
    assert tuple(draw_tracks(img, [tentative], [], scale=2)[20, 30]) != track_colour(7)  # not drawn
