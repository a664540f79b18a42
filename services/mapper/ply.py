"""Point clouds and maps as PLY files (DESIGN.md section 5): binary little-endian written, binary or ASCII read.

Per-vertex properties beyond x, y, z travel as further columns (colours, confidence, the keyframe
a point was last seen from); the keyframes' times and poses as `comment keyframe` header lines, so
`etam eval map` can score each point in the view it was measured from.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from services.mapper.cloud import VoxelMap

_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
          "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2",
          "int32": "<i4", "uint32": "<u4", "float32": "<f4", "float64": "<f8"}
_NAMES = {np.dtype(v).str: k for k, v in reversed(list(_TYPES.items())) if not k[-1].isdigit()}


class PlyError(ValueError):
    """A PLY file this reader cannot read; the message names the file and what is wrong."""


def write_ply(path: Path, points: np.ndarray, fields: dict[str, np.ndarray] | None = None,
              comments: list[str] | None = None) -> None:
    """Writes points (N x 3) and per-point `fields` (1-D arrays of N; `red`/`green`/`blue` as uint8)."""
    points = np.asarray(points, np.float32).reshape(-1, 3)
    columns = {"x": points[:, 0], "y": points[:, 1], "z": points[:, 2]}
    columns.update({k: np.asarray(v) for k, v in (fields or {}).items()})
    table = np.empty(len(points), [(k, v.dtype.newbyteorder("<")) for k, v in columns.items()])
    for k, v in columns.items():
        table[k] = v
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments or []),
              f"element vertex {len(points)}",
              *(f"property {_NAMES[table.dtype[k].str]} {k}" for k in columns), "end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(table.tobytes())


def read_ply(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray], list[str]]:
    """Points (N x 3 float32), the other vertex properties by name, and the header's comments."""
    with open(path, "rb") as f:
        data = f.read()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise PlyError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    body_at = data.index(b"\n", end) + 1
    fmt, count, props, comments, in_vertex = None, None, [], [], False
    for line in data[:end].decode("ascii", "replace").splitlines()[1:]:
        words = line.split()
        if not words:
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "comment":
            comments.append(line[len("comment "):])
        elif words[0] == "element":
            in_vertex = words[1] == "vertex"
            if in_vertex:
                count = int(words[2])
            elif count is not None:
                break  # elements after the vertices (faces) are not read
        elif words[0] == "property" and in_vertex:
            if words[1] == "list" or words[1] not in _TYPES:
                raise PlyError(f"{path}: unsupported vertex property '{line.strip()}'")
            props.append((words[2], _TYPES[words[1]]))
    if count is None or not {"x", "y", "z"} <= {name for name, _ in props}:
        raise PlyError(f"{path}: no vertex element with x, y and z properties")
    dtype = np.dtype(props)
    if fmt == "binary_little_endian":
        need = count * dtype.itemsize
        if len(data) - body_at < need:
            raise PlyError(f"{path}: truncated: {count} vertices need {need} bytes after the header, "
                           f"found {len(data) - body_at}")
        table = np.frombuffer(data, dtype, count, body_at)
    elif fmt == "ascii":
        rows = data[body_at:].decode("ascii", "replace").split("\n")[:count]
        try:
            values = np.array([r.split()[:len(props)] for r in rows], np.float64).reshape(-1, len(props))
        except ValueError as e:
            raise PlyError(f"{path}: bad vertex line in the ASCII body ({e})") from None
        if len(values) < count:
            raise PlyError(f"{path}: truncated: {count} vertices declared, {len(values)} found")
        table = np.empty(count, dtype)
        for i, (name, _) in enumerate(props):
            table[name] = values[:, i]
    else:
        raise PlyError(f"{path}: unsupported PLY format '{fmt}' (binary_little_endian and ascii are read)")
    points = np.stack([table["x"], table["y"], table["z"]], axis=1).astype(np.float32)
    return points, {name: table[name].copy() for name, _ in props if name not in ("x", "y", "z")}, comments


def write_map(path: Path, cloud: VoxelMap, note: str) -> int:
    """Writes a map (its points with confidence, observation count and last keyframe) with one `keyframe`
    comment line per keyframe (index, t_us, tx ty tz qx qy qz qw); the number of points."""
    points, counts, conf, which = cloud.points()
    comments = [f"{note}; keyframe lines: index t_us tx ty tz qx qy qz qw"]
    for i, (t_us, R, p) in enumerate(cloud.views):
        pose = (*p, *Rotation.from_matrix(R).as_quat())
        comments.append(f"keyframe {i} {t_us} " + " ".join(f"{v:.9g}" for v in pose))
    write_ply(path, points, {"confidence": conf, "observations": counts.astype(np.uint32),
                             "keyframe": which.astype(np.uint32)}, comments)
    return len(points)


def read_map(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A map from `write_map`: its points and, per point, the time (us) of the keyframe that last saw it."""
    points, fields, comments = read_ply(path)
    times = {int(w[1]): int(w[2]) for c in comments if len(w := c.split()) >= 3 and w[0] == "keyframe"}
    if "keyframe" not in fields or not times:
        raise PlyError(f"{path}: not a map from etam map (no keyframe property or keyframe comments)")
    missing = set(np.unique(fields["keyframe"]).tolist()) - set(times)
    if missing:
        raise PlyError(f"{path}: points of keyframes {sorted(missing)[:5]} that no comment line describes")
    return points, np.array([times[k] for k in fields["keyframe"].tolist()], np.int64)
