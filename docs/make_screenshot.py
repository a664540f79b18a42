"""Make docs/dashboard.png: `etam up` on the 6-DoF simulator (camera, tracker, mapper, dashboard) plus the
heat-map plug-in, seen in headless Chromium.

    python docs/make_screenshot.py      (needs chromium: apt-get install chromium)
"""

import re
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.browser import Browser  # noqa: E402
from tests.conftest import etam_argv, free_port  # noqa: E402


def main() -> None:
    router = f"tcp/127.0.0.1:{free_port()}"
    up = subprocess.Popen(etam_argv("up", "--source", "sim:6dof", "--rig", "drone1", "--listen", router, "--web-port", str(free_port()),
                                    "--duration", "120", "--log-level", "WARNING"),
                          cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    plugin = subprocess.Popen([sys.executable, "examples/heatmap_plugin.py", "--connect", router, "--rig", "drone1"],
                              cwd=ROOT, stderr=subprocess.DEVNULL)
    try:
        url = re.search(r"http://\S+", up.stdout.readline()).group(0)
        with Browser(width=1600, height=1000) as browser:
            browser.goto(url)
            time.sleep(55)  # the map grows by a keyframe every few seconds; software WebGL renders below 1 fps
            browser.evaluate("document.querySelectorAll('.mantine-Notification-closeButton, "
                             "button[class*=CloseButton]').forEach(b => b.click())")
            time.sleep(3)
            (ROOT / "docs" / "dashboard.png").write_bytes(browser.screenshot())
    finally:
        plugin.terminate()
        up.terminate()
        plugin.wait(10)
        up.wait(20)


if __name__ == "__main__":
    main()
