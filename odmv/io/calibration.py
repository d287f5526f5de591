"""A rig from an OpenCV-style calibration file (YAML or JSON), for predicting from a real rig.

Schema (docs/training.md, "Predict"), OpenCV conventions (pixel centres at integers,
``X_projector = R @ X_camera + t`` as from ``cv2.stereoCalibrate``), lengths in mm::

    camera:
      image_size: [width, height]        # the size K refers to
      K: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
      dist: [k1, k2, p1, p2]             # a fifth coefficient (k3) must be 0
    reference_plane_mm: 150.0            # the flat reference plane, perpendicular to the
                                         # camera axis, this far from the camera centre
    projectors:
      right:                             # views by the rig's names: right, down, left, up
        image_size: [1920, 1080]
        K: [[...], [...], [...]]
        R: [[...], [...], [...]]         # camera -> projector rotation
        t: [tx, ty, tz]                  # camera -> projector translation (mm)
        phase_axis: u                    # the projector axis the fringe phase runs along

The world frame is odmv's (odmv/rig.py): origin where the camera axis meets the reference
plane, +z towards the camera, so the reference phase and the point clouds use the same
conventions as the simulator's rig.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from odmv.rig import VIEW_NAMES, Camera, Projector, rig_geometry

_WORLD_TO_CAMERA = np.diag([1.0, -1.0, -1.0])  # the camera looks down -z, rows run along -y


class CalibrationError(ValueError):
    """A one-line error naming the calibration file and the entry at fault."""


def _matrix(path, key, value, shape) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.isfinite(a).all():
        raise CalibrationError(f"{path}: {key} must be a finite {'x'.join(map(str, shape))} array")
    return a


def _opencv_to_corner_origin(K: np.ndarray) -> np.ndarray:
    """OpenCV puts pixel centres at integers; odmv puts the top-left corner at 0."""
    K = K.copy()
    K[0, 2] += 0.5
    K[1, 2] += 0.5
    return K


@dataclass(frozen=True)
class CalibratedRig:
    """Duck-types :class:`odmv.rig.Rig` where prediction and datasets need it: ``camera_at``,
    ``projectors``, ``geometry``; ``source`` is the file's content (a dataset's manifest keeps
    it)."""

    K: np.ndarray  # camera intrinsics at ``size`` (corner origin)
    dist: np.ndarray
    size: tuple[int, int]  # (width, height) K refers to
    plane_mm: float
    devices: dict[str, Projector]
    source: dict = field(default_factory=dict, compare=False)

    def camera_at(self, width_px: int, height_px: int | None = None) -> Camera:
        height_px = width_px if height_px is None else height_px
        scale = np.diag([width_px / self.size[0], height_px / self.size[1], 1.0])
        center = np.array([0.0, 0.0, self.plane_mm])
        R = _WORLD_TO_CAMERA
        return Camera(scale @ self.K, self.dist, R, -R @ center, width_px, height_px)

    def projectors(self) -> dict[str, Projector]:
        return dict(self.devices)

    def geometry(self, width_px: int, height_px: int | None = None) -> dict:
        return rig_geometry(self, width_px, height_px)


def load_calibration(path: str | Path) -> CalibratedRig:
    path = Path(path)
    if not path.is_file():
        raise CalibrationError(f"{path}: no such calibration file")
    try:
        text = path.read_text()
        data = json.loads(text) if path.suffix.lower() == ".json" else yaml.safe_load(text)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, yaml.YAMLError) as e:
        raise CalibrationError(
            f"{path}: not readable YAML or JSON ({str(e).splitlines()[0]})"
        ) from None
    return parse_calibration(data, path)


def parse_calibration(data, path) -> CalibratedRig:
    """A calibration's content (the schema above) -> the rig; ``path`` names it in errors."""
    if not isinstance(data, dict) or not {"camera", "projectors", "reference_plane_mm"} <= set(
        data
    ):
        raise CalibrationError(f"{path}: needs camera, projectors and reference_plane_mm")
    cam = data["camera"]
    size = tuple(int(x) for x in _matrix(path, "camera.image_size", cam.get("image_size"), (2,)))
    K = _opencv_to_corner_origin(_matrix(path, "camera.K", cam.get("K"), (3, 3)))
    dist = np.asarray(cam.get("dist", [0, 0, 0, 0]), float)
    if dist.shape not in ((4,), (5,)) or (dist.shape == (5,) and dist[4] != 0):
        raise CalibrationError(f"{path}: camera.dist must be [k1, k2, p1, p2] (k3 = 0)")
    plane = float(data["reference_plane_mm"])
    if not plane > 0:
        raise CalibrationError(f"{path}: reference_plane_mm must be positive")
    center = np.array([0.0, 0.0, plane])
    t_wc = -_WORLD_TO_CAMERA @ center
    devices = {}
    for name, p in (data["projectors"] or {}).items():
        if name not in VIEW_NAMES:
            raise CalibrationError(f"{path}: projector {name!r} is not one of {VIEW_NAMES}")
        key = f"projectors.{name}"
        R_cp = _matrix(path, f"{key}.R", p.get("R"), (3, 3))
        t_cp = _matrix(path, f"{key}.t", p.get("t"), (3,))
        w, h = (int(x) for x in _matrix(path, f"{key}.image_size", p.get("image_size"), (2,)))
        axis = p.get("phase_axis", "u")
        if axis not in ("u", "v"):
            raise CalibrationError(f"{path}: {key}.phase_axis must be u or v")
        K_p = _opencv_to_corner_origin(_matrix(path, f"{key}.K", p.get("K"), (3, 3)))
        R = R_cp @ _WORLD_TO_CAMERA
        devices[name] = Projector(name, K_p, R, R_cp @ t_wc + t_cp, w, h, axis)
    if not devices:
        raise CalibrationError(f"{path}: no projectors")
    devices = {v: devices[v] for v in VIEW_NAMES if v in devices}  # the rig's order, not the file's
    source = json.loads(json.dumps(data))  # plain JSON types, as a manifest stores it
    return CalibratedRig(K, dist[:4], size, plane, devices, source)


def calibration_of(rig, width_px: int, height_px: int) -> dict:
    """A rig (the twin's, or a calibrated one) as the content of a calibration file (the
    schema above) for a camera of ``width_px`` x ``height_px``: what
    :func:`parse_calibration` reads back into the same rig."""
    cam = rig.camera_at(width_px, height_px)
    centre = np.array([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])  # OpenCV's pixel centres
    projectors = {}
    for name, p in rig.projectors().items():
        R_cp = p.R @ _WORLD_TO_CAMERA.T
        projectors[name] = {
            "image_size": [int(p.width_px), int(p.height_px)],
            "K": (p.K - centre).tolist(),
            "R": R_cp.tolist(),
            "t": (p.t - R_cp @ cam.t).tolist(),
            "phase_axis": p.phase_axis,
        }
    return {
        "camera": {
            "image_size": [int(width_px), int(height_px)],
            "K": (cam.K - centre).tolist(),
            "dist": [float(d) for d in cam.dist],
        },
        "reference_plane_mm": float(cam.center[2]),
        "projectors": projectors,
    }
