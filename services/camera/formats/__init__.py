"""Event file readers and writers (DESIGN.md section 7), chosen by content rather than extension."""

from __future__ import annotations

from pathlib import Path

from services.camera.formats import aedat2, aedat4, arrays, ecd, hdf5, prophesee
from services.camera.formats.recording import Calibration, FormatError, Recording, Truth

__all__ = ["Calibration", "FormatError", "Recording", "Truth", "open_recording", "SUPPORTED"]

SUPPORTED = ("ETAM/DSEC HDF5, ECD text, AEDAT 4.0, jAER AEDAT 2.0 (DAVIS240, DVS128), Prophesee RAW (EVT 2.0, 3.0) "
             "and DAT, "
             "MATLAB `events`, npz, N-MNIST .bin")


def open_recording(path: str | Path) -> Recording:
    """Open any supported event file or ECD folder, detecting the format from its first bytes."""
    path = Path(path)
    if not path.exists():
        raise FormatError(path, "no such file or folder")
    if path.is_dir():
        return ecd.EcdRecording(path)
    with open(path, "rb") as f:
        head = f.read(4096)
    if not head:
        raise FormatError(path, "the file is empty")
    if head.startswith(hdf5.MAGIC):
        return hdf5.H5Recording(path)
    if head.startswith(aedat4.MAGIC):
        return aedat4.Aedat4Recording(path)
    if head.startswith(aedat2.MAGIC):
        return aedat2.Aedat2Recording(path)
    if head.startswith(b"% "):
        return prophesee.open_prophesee(path)
    if head.startswith(arrays.MAT_MAGIC):
        return arrays.MatRecording(path)
    if head.startswith(arrays.NPZ_MAGIC):
        return arrays.NpzRecording(path)
    if ecd.looks_like(head):
        return ecd.EcdRecording(path)
    if path.suffix.lower() == ".bin" and arrays.looks_like_nmnist(head):  # no header to tell it
        return arrays.NmnistRecording(path)
    raise FormatError(path, f"unknown event file format (first bytes {head[:16]!r}); readable: {SUPPORTED}")
