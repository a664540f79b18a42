"""The dashboard of a running `etam up` in a real headless Chromium, checked from its pixels: the map
point cloud in the 3D view, the live event image with boxes, the health table, and two controls (pause
freezes the view; reset map empties the map)."""

from __future__ import annotations

import re
import subprocess
import threading
import time

import cv2
import numpy as np
import pytest

from services.messages import Stats, Tracks
from tests.browser import CHROMIUM, Browser
from tests.conftest import ROOT, client_session, etam_argv, free_port, wait_for
from web.render import track_colour

pytestmark = [pytest.mark.slow, pytest.mark.skipif(
    CHROMIUM is None, reason="chromium is not installed (.ci/run installs it; or: apt-get install chromium)",
)]

PLUGIN_BOX = (60, 50, 120, 80)  # x, y, w, h (px) of the plug-in's one track, id 7
MAP_POINTS = 300  # the semi-dense map of sim:6dof grows by 100-300 points a keyframe, one every 1-3 s
IMAGES = "Array.from(document.images).filter(i => i.src.startsWith('blob:') && i.naturalWidth >= 692)"


def _publish_plugin_tracks(endpoint: str, rig: str, stop: threading.Event) -> None:
    """A plug-in as any user would write one: Tracks on its own key, which the dashboard has never heard of."""
    with client_session(endpoint) as session:
        pub = session.declare_publisher(f"etam/{rig}/plugin/boxes/tracks")
        other = session.declare_publisher(f"etam/{rig}-b/plugin/probe/stats")  # a second rig on the network
        seq = 0
        while not stop.is_set():
            msg = Tracks.from_boxes(seq, [7], [PLUGIN_BOX], xyz=np.array([[0.3, 0.2, 2.0]], np.float32))
            msg.seq = seq
            pub.put(msg.encode())
            if seq % 10 == 0:
                other.put(Stats(service="plugin", name="probe", keys=[]).encode())
            seq += 1
            stop.wait(0.1)
        pub.undeclare()
        other.undeclare()


def _rect(browser: Browser, js_element: str) -> tuple[int, int, int, int]:
    """Where an element is on the page (x, y, w, h); the event image's element is renewed with each frame."""
    r = wait_for(lambda: browser.evaluate(f"(() => {{ const e = {js_element}; if (!e) return null; "
                                          "const r = e.getBoundingClientRect(); "
                                          "return r.width > 0 ? [r.left, r.top, r.width, r.height] : null; })()"),
                 10, f"the element {js_element}")
    return tuple(int(round(v)) for v in r)


def _shot(browser: Browser) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(browser.screenshot(), np.uint8), cv2.IMREAD_COLOR)
    assert img is not None
    return img[..., ::-1]  # RGB


def _crop(img: np.ndarray, rect: tuple[int, int, int, int]) -> np.ndarray:
    x, y, w, h = rect
    return img[y:y + h, x:x + w].astype(np.int16)


def _vivid(img: np.ndarray) -> np.ndarray:
    """Where the colour is saturated (the point cloud's colour map; the grid, the page and the text are grey)."""
    hsv = cv2.cvtColor(np.ascontiguousarray(img.astype(np.uint8)), cv2.COLOR_RGB2HSV)
    return (hsv[..., 1] > 120) & (hsv[..., 2] > 60)


def _type(browser: Browser, old: str, new: str) -> None:
    """Replace the text of the input that holds `old` as a user typing would (React sees an input event)."""
    assert browser.evaluate(
        f"(() => {{ const i = Array.from(document.querySelectorAll('input')).find(e => e.value === {old!r}); "
        "if (!i) return false; Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, 'value').set"
        f".call(i, {new!r}); i.dispatchEvent(new Event('input', {{bubbles: true}})); return true; }})()"), old


def _hue_distance(pixels: np.ndarray, rgb: tuple[int, int, int]) -> np.ndarray:
    """Hue difference (OpenCV's 0-180 scale) of each pixel from `rgb`; 90 for pixels without colour (a thin
    line in a downscaled image keeps its hue but not its brightness)."""
    hsv = cv2.cvtColor(np.ascontiguousarray(pixels.reshape(1, -1, 3).astype(np.uint8)), cv2.COLOR_RGB2HSV)[0]
    ref = int(cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2HSV)[0, 0, 0])
    d = np.abs(hsv[:, 0].astype(int) - ref)
    return np.where(hsv[:, 1] > 80, np.minimum(d, 180 - d), 90)


def _text(browser: Browser) -> str:
    return browser.evaluate("document.body ? document.body.innerText : ''") or ""


def _wait_text(browser: Browser, expected: tuple[str, ...], timeout_s: float) -> str:
    """The page's text once it holds every `expected` string; else fail saying which are missing and what the
    page shows."""
    deadline, text = time.monotonic() + timeout_s, ""
    while time.monotonic() < deadline:
        text = _text(browser)
        if all(s in text for s in expected):
            return text
        time.sleep(0.2)
    missing = [s for s in expected if s not in text]
    raise AssertionError(f"after {timeout_s} s the page lacks {missing}; it shows {text[:1500]!r}")


def _click(browser: Browser, text: str) -> None:
    assert browser.evaluate(f"(() => {{ const b = Array.from(document.querySelectorAll('button'))"
                            f".find(b => b.innerText.includes({text!r})); if (b) b.click(); return !!b; }})()"), text


@pytest.mark.timeout(420)
def test_dashboard_draws_map_events_boxes_and_obeys_pause_and_reset(rig: str, tmp_path) -> None:  # noqa: ANN001
    endpoint, log = f"tcp/127.0.0.1:{free_port()}", tmp_path / "up.log"
    with log.open("w") as err:
        proc = subprocess.Popen(
            etam_argv("up", "--source", "sim:6dof", "--rig", rig, "--web-port", str(free_port()), "--listen",
                      endpoint, "--duration", "300", "--log-level", "WARNING"),
            cwd=ROOT, stdout=subprocess.PIPE, stderr=err, text=True,
        )
    stop = threading.Event()
    plugin = threading.Thread(target=_publish_plugin_tracks, args=(endpoint, rig, stop), daemon=True)
    try:
        line = proc.stdout.readline()
        url = re.search(r"http://\S+", line)
        assert url, f"no dashboard URL printed: {line!r}"
        plugin.start()
        with Browser() as browser:
            browser.goto(url.group(0))
            # services appear by their liveliness tokens, their keys with their first Stats (a clean clone
            # compiles kernels first)
            expected = ("camera/cam0", "tracker/objects", "mapper/map", "web/web", "→ tracks", "→ events", "→ points")
            text = _wait_text(browser, expected, 180)
            assert f"ETAM · {rig}" in text
            points = wait_for(lambda: int(m.group(1).replace(",", "")) if (m := re.search(
                r"([\d,]+) points shown", _text(browser))) and int(
                m.group(1).replace(",", "")) >= MAP_POINTS else 0, 150, f"{MAP_POINTS} map points", period_s=1.0)
            wait_for(lambda: browser.evaluate(f"{IMAGES}.length"), 30, "the live event image", period_s=0.5)
            time.sleep(3)  # the software renderer draws the scene once the cloud has arrived
            image = _rect(browser, f"{IMAGES}[0]")
            canvas = _rect(browser, "document.querySelector('canvas')")
            scene = (canvas[0], canvas[1], image[0] - 20 - canvas[0], canvas[3])  # left of the control panel
            first = _shot(browser)
            (tmp_path / "dashboard.png").write_bytes(cv2.imencode(".png", first[..., ::-1])[1].tobytes())

            # the event image: events in polarity colours, and the plug-in's box drawn in id 7's colour
            ev = _crop(first, image)
            scale = image[2] / 692
            assert np.mean(np.abs(ev - 30).max(axis=2) > 60) > 0.01, "no events drawn"
            x, y, w, h = (np.array(PLUGIN_BOX) * 2 * scale).astype(int)
            top = max((ev[row, x + 4:x + w - 4] for row in (y - 1, y, y + 1)), key=lambda px: px.sum())
            assert np.median(_hue_distance(top, track_colour(7))) < 10, "the plug-in's box is not drawn"
            # it changes within seconds: back to back, two shots once matched while a slow simulator caught up
            deadline, change = time.monotonic() + 10, 0.0
            while change <= 1.0 and time.monotonic() < deadline:
                change = float(np.abs(_crop(_shot(browser), image) - ev).mean())
            assert change > 1.0, "the event image does not change in 10 s"

            # save map: the mapper writes the file it is told, and its reply is shown
            ply = tmp_path / "saved.ply"
            _type(browser, "map.ply", str(ply))
            time.sleep(1)
            _click(browser, "Save map")
            _wait_text(browser, ("save done",), 30)
            assert ply.read_bytes().startswith(b"ply") and ply.stat().st_size > 1000

            # pause: the whole view freezes (the event image, the camera moving in the 3D view)
            _click(browser, "Pause view")
            _wait_text(browser, ("Resume view",), 10)
            time.sleep(2)
            paused, later = _shot(browser), _shot(browser)
            assert np.abs(_crop(later, image) - _crop(paused, image)).mean() < 0.5, "pause did not freeze the image"
            assert np.abs(_crop(later, scene) - _crop(paused, scene)).mean() < 0.5, "pause did not freeze the scene"

            # reset map (while paused, so nothing else moves): the colour-mapped points go, nothing comes
            _click(browser, "Reset map")
            _wait_text(browser, ("reset done",), 30)
            _wait_text(browser, ("No map yet",), 10)
            time.sleep(3)
            before, after = _vivid(_crop(later, scene)), _vivid(_crop(_shot(browser), scene))
            gone, came = np.count_nonzero(before & ~after), np.count_nonzero(after & ~before)
            assert gone > 300, f"no point cloud drawn, or reset map left it ({gone} vivid pixels went)"
            assert came < 0.1 * gone, f"{came} vivid pixels appeared on reset"
            _click(browser, "Resume view")
            time.sleep(2)
            assert np.abs(_crop(_shot(browser), image) - _crop(later, image)).mean() > 1.0, "resume did not resume"

            # the rig chooser: the other rig's services replace this one's
            browser.evaluate("Array.from(document.querySelectorAll('input')).find(e => e.value === "
                             f"{rig!r}).click()")
            wait_for(lambda: browser.evaluate("(() => { const o = Array.from(document.querySelectorAll("
                                              f"'[role=option]')).find(o => o.innerText.trim() === {rig + '-b'!r});"
                                              " if (o) o.click(); return !!o; })()"), 10, "the other rig offered")
            text = _wait_text(browser, (f"ETAM · {rig}-b", "plugin/probe"), 20)
            assert "camera/cam0" not in text
        assert points >= MAP_POINTS
    except AssertionError as exc:  # a failure on a CI machine must be readable from its message alone
        raise AssertionError(f"{exc}\netam up logged: {log.read_text(errors='replace')[-3000:]!r}") from None
    finally:
        stop.set()
        plugin.join(10)
        proc.terminate()
        proc.wait(20)
