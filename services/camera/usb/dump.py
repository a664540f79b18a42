"""`etam usb-decode`: a raw dump of a camera's bulk stream decoded into an event file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tqdm import tqdm

from services.camera.formats.hdf5 import H5Writer
from services.camera.usb.protocol import MODELS
from services.camera.usb.words import WordDecoder

CHUNK_BYTES = 1 << 22  # even: a chunk never splits a word


def decode_dump(model: str, dump: Path, out: Path, progress: bool = True) -> dict[str, Any]:
    """Decode `dump` (the bytes of the bulk endpoint, as captured) as `model`'s words into HDF5 `out`."""
    if model not in MODELS:
        raise ValueError(f"model {model!r} is not one of {', '.join(MODELS)}")
    if not dump.is_file():
        raise FileNotFoundError(f"{dump}: no such file")
    dvx, width, height = MODELS[model]
    decoder = WordDecoder(dvx, width, height)
    counts = {"events": 0, "imu_samples": 0, "timestamp_resets": 0, "dropped_words": 0}
    with H5Writer(out, width, height) as writer, dump.open("rb") as f, \
            tqdm(total=dump.stat().st_size, unit="B", unit_scale=True, desc=dump.name, disable=not progress) as bar:
        while chunk := f.read(CHUNK_BYTES):
            d = decoder.decode(chunk)
            writer.write(d.events)
            counts["events"] += len(d.events)
            counts["imu_samples"] += len(d.imu_t)
            counts["timestamp_resets"] += d.resets
            counts["dropped_words"] += d.dropped
            bar.update(len(chunk))
    return {"input": str(dump), "model": model, "output": str(out), "width": width, "height": height, **counts}
