"""A plug-in service in one file: an event-activity heat map, published as an Image the dashboard shows.

Run it beside a rig (`etam up` in another terminal):

    python examples/heatmap_plugin.py --connect tcp/127.0.0.1:7447

It subscribes to every camera's events and publishes `etam/<rig>/heatmap/heatmap/frame` ten times a
second; the dashboard lists it with its rates and draws every `.../frame` it sees.
"""

import argparse
import asyncio

import cv2
import numpy as np

from services import config, keys
from services.messages import EventPacket, image_from_array
from services.runtime import Service, ServiceOptions
from services.tracker.objects.accumulator import DecayedAccumulator


class HeatmapService(Service):
    kind = "heatmap"
    heat: DecayedAccumulator | None = None
    t_us = 0

    async def main(self) -> None:
        drawing = asyncio.create_task(self.draw(self.publisher("frame")))
        try:
            async for _key, packet in self.subscribe(keys.events(self.rig), EventPacket, policy="fifo"):
                if self.heat is None:
                    self.heat = DecayedAccumulator(packet.width, packet.height, tau_us=200_000)
                self.heat.accept(packet.events)
                self.t_us = packet.stamp
        finally:
            drawing.cancel()

    async def draw(self, frames) -> None:  # noqa: ANN001 - an Output
        while True:
            await asyncio.sleep(0.1)
            if self.heat is not None:
                counts = self.heat.generate(self.t_us)
                pixels = np.clip(counts * 64, 0, 255).astype(np.uint8)
                frames.publish(image_from_array(self.t_us, cv2.applyColorMap(pixels, cv2.COLORMAP_INFERNO)))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--connect", action="append", help="endpoint of the rig (default tcp/127.0.0.1:7447)")
    parser.add_argument("--rig", help="rig name (default: host name)")
    args = parser.parse_args()
    settings = config.resolve(connect=args.connect or ["tcp/127.0.0.1:7447"])
    raise SystemExit(HeatmapService(ServiceOptions(config.resolve_rig(args.rig), "heatmap", settings)).run())
