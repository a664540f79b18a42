"""The dashboard in a real headless Chromium: live services table, event image, 3D canvas."""

from __future__ import annotations

import re
import subprocess
import time

import cv2
import numpy as np
import pytest

from tests.browser import CHROMIUM, Browser
from tests.conftest import ROOT, etam_argv, free_port, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed")]


def test_dashboard_shows_live_services_events_and_boxes(rig: str, tmp_path) -> None:  # noqa: ANN001
    proc = subprocess.Popen(
        etam_argv("up", "--rig", rig, "--web-port", str(free_port()), "--listen", f"tcp/127.0.0.1:{free_port()}",
                  "--duration", "90", "--log-level", "WARNING"),
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
    )
    try:
        line = proc.stdout.readline()
        url = re.search(r"http://\S+", line)
        assert url, f"no dashboard URL printed: {line!r}"
        with Browser() as browser:
            browser.goto(url.group(0))
            text = wait_for(lambda: (t := browser.evaluate("document.body.innerText") or "")
                            and all(s in t for s in ("camera/cam0", "tracker/objects", "web/web")) and t,
                            60, "all three services in the dashboard table", period_s=1.0)
            assert f"ETAM · {rig}" in text and "→ tracks" in text and "→ events" in text
            assert browser.evaluate("document.querySelectorAll('canvas').length") >= 1  # the 3D scene
            # the live event image: on a clean clone its first frame may come long after the table (kernels compile)
            wait_for(lambda: browser.evaluate("Array.from(document.images).some(i => i.src.startsWith('blob:') "
                                              "&& i.naturalWidth >= 346)"),
                     60, "the live event image", period_s=0.5)
            time.sleep(3)
            png = browser.screenshot()
        (tmp_path / "dashboard.png").write_bytes(png)
        img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
        assert img is not None and img.std() > 10  # not a blank page
    finally:
        proc.terminate()
        proc.wait(20)
