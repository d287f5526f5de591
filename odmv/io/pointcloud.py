"""Point clouds from depth maps: camera-frame points of a depth map and binary PLY files."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from odmv.io.atomic import write_bytes
from odmv.rig import Camera


def point_cloud(depth_mm: np.ndarray, cam: Camera, keep: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame points (N x 3, mm) of the pixel centres at their depth: pixels with a
    finite depth, and only those in ``keep`` where given."""
    _, d = cam.centre_rays()
    d_cam = d.reshape(-1, 3) @ cam.R.T  # camera-frame directions
    pts = d_cam / d_cam[:, 2:3] * depth_mm.reshape(-1, 1)
    ok = np.isfinite(pts).all(1)
    if keep is not None:
        ok &= keep.reshape(-1)
    return pts[ok]


def write_ply(
    path: Path,
    points: np.ndarray,
    grey: np.ndarray | None = None,
    uncertainty_mm: np.ndarray | None = None,
) -> Path:
    """Binary little-endian PLY of float32 xyz points (grey: uint8 colour per point, written
    as equal red, green and blue; ``uncertainty_mm``: each point's interval half width, the
    float property ``uncertainty``), atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if grey is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if uncertainty_mm is not None:
        fields += [("uncertainty", "<f4")]
    rows = np.empty(len(points), dtype=fields)
    for k, axis in enumerate("xyz"):
        rows[axis] = points[:, k]
    if grey is not None:
        for channel in ("red", "green", "blue"):
            rows[channel] = grey
    if uncertainty_mm is not None:
        rows["uncertainty"] = uncertainty_mm
    types = {"<f4": "float", "u1": "uchar"}
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment odmv depth, camera frame, mm\n"
        + ("comment uncertainty: interval half width, mm\n" if uncertainty_mm is not None else "")
        + f"element vertex {len(points)}\n"
        + "".join(f"property {types[t]} {name}\n" for name, t in fields)
        + "end_header\n"
    )
    return write_bytes(path, header.encode("ascii") + rows.tobytes())
