"""The paper's multi-view FPP rig as data: one camera looking straight down, four projectors.

World frame (all lengths in mm): the origin is where the camera axis meets the reference plane
(the base plane the objects stand on), +z points up towards the camera, +x is image-right and
+y is image-up. The camera frame is x right, y down, z along the viewing direction (OpenCV), so
``depth`` = camera-frame z = ``working_distance_mm - z_world`` for any point.

Pixel convention (camera and projectors): continuous coordinates with the top-left *corner* of
the image at (0, 0); the centre of pixel (row i, column j) is at (j + 0.5, i + 0.5). OpenCV puts
pixel centres at integers: subtract 0.5 from the principal point to convert.

Projectors are one unit turned about the camera axis by 0, 90, 180 and 270 degrees and tilted
by ``tilt_deg`` towards the reference point. Their long axis (columns) lies along their baseline,
so every projector's fringe phase runs along its column coordinate ``u``: vertical stripes in
the image for right/left, horizontal stripes for down/up.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

#: Canonical view order: the paper's projector indices 1-4 (Fig. 3d).
VIEW_NAMES: tuple[str, ...] = ("right", "down", "left", "up")

#: Subsets used by the paper's view-count experiment (Sec. III.A), in canonical order.
VIEW_SETS: dict[int, tuple[str, ...]] = {
    4: ("right", "down", "left", "up"),
    3: ("right", "left", "up"),
    2: ("right", "up"),
    1: ("right",),
}

# Unit direction (world x, y) from the camera axis towards each projector. "down" in the image
# is world -y because image rows grow downwards.
_AZIMUTH_XY: dict[str, tuple[float, float]] = {
    "right": (1.0, 0.0),
    "down": (0.0, -1.0),
    "left": (-1.0, 0.0),
    "up": (0.0, 1.0),
}


def check_views(views: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Return ``views`` in canonical order; raise ValueError naming any unknown view."""
    if not views:
        raise ValueError(f"no view named; name at least one of {', '.join(VIEW_NAMES)}")
    unknown = [v for v in views if v not in VIEW_NAMES]
    if unknown:
        raise ValueError(f"unknown view name(s) {unknown}; known views are {list(VIEW_NAMES)}")
    if len(set(views)) != len(views):
        raise ValueError(f"duplicate view names in {list(views)}")
    return tuple(v for v in VIEW_NAMES if v in views)


def size_hw(
    resolution: int | list[int] | tuple[int, int], key: str = "resolution"
) -> tuple[int, int]:
    """A resolution setting (one int for square images, or [height, width]) as (H, W); a
    ValueError naming ``key`` for anything but one or two positive whole numbers."""
    sizes = [resolution] if isinstance(resolution, (int, float, str)) else list(resolution)
    if len(sizes) not in (1, 2):
        raise ValueError(f"{key}={resolution}: one size (square) or [height, width] in pixels")
    h, *w = (whole_number(n, key, 1, "image sizes are at least 1 px") for n in sizes)
    return h, (w[0] if w else h)


def whole_number(value, key: str, low: int, what: str) -> int:
    """Setting ``key``'s ``value`` as an int of at least ``low``, else a ValueError that names
    the key and says ``what`` is allowed."""
    text = str(value).strip()
    if isinstance(value, (bool, float)) or not text.lstrip("+-").isdigit():
        raise ValueError(f"{key}={value!r}: not a whole number; {what}")
    number = int(text)
    if number < low:
        raise ValueError(f"{key}={number}: {what}")
    return number


@dataclass(frozen=True)
class CameraSpec:
    """Camera hardware (paper Sec. II.B): 4800x4800 px, 3.2 um pixels, 35.47 mm square field.

    ``focal_length_mm`` is the pinhole (image-side) focal length; when None it follows from the
    field and the working distance, when given it overrides ``field_mm``. Distortion is
    Brown-Conrady on normalized coordinates (OpenCV's k1, k2, p1, p2).
    """

    width_px: int = 4800
    height_px: int = 4800
    pixel_um: float = 3.2
    field_mm: tuple[float, float] = (35.47, 35.47)
    working_distance_mm: float = 150.0
    focal_length_mm: float | None = None
    distortion: tuple[float, float, float, float] = (-0.05, 0.01, 1e-4, -1e-4)

    def __post_init__(self):
        _positive("camera", self, ("width_px", "height_px", "pixel_um", "working_distance_mm"))
        _positive("camera", self, ("field_mm",) if self.focal_length_mm is None else ())
        _positive("camera", self, ("focal_length_mm",) if self.focal_length_mm is not None else ())

    @property
    def sensor_mm(self) -> tuple[float, float]:
        return (self.width_px * self.pixel_um * 1e-3, self.height_px * self.pixel_um * 1e-3)

    @property
    def focal_mm(self) -> float:
        if self.focal_length_mm is not None:
            return float(self.focal_length_mm)
        return self.working_distance_mm * self.sensor_mm[0] / self.field_mm[0]

    @property
    def field_at_reference_mm(self) -> tuple[float, float]:
        """Field of view on the reference plane implied by the focal length."""
        sw, sh = self.sensor_mm
        f = self.focal_mm
        return (sw * self.working_distance_mm / f, sh * self.working_distance_mm / f)


@dataclass(frozen=True)
class ProjectorSpec:
    """Projector hardware (paper Sec. II.B): 1920x1080 px, 40 mm x 23 mm field, 26 deg tilt.

    ``distance_mm`` is measured along the projector axis from its centre of projection to the
    reference point; the default puts the projectors at about the camera's height.
    """

    width_px: int = 1920
    height_px: int = 1080
    field_mm: tuple[float, float] = (40.0, 23.0)
    tilt_deg: float = 26.0
    distance_mm: float = 167.0

    def __post_init__(self):
        _positive("projector", self, ("width_px", "height_px", "field_mm", "distance_mm"))
        if not -90 < self.tilt_deg < 90:
            raise ValueError(f"projector.tilt_deg: {self.tilt_deg}; between -90 and 90 degrees")


def _positive(part: str, spec, names: tuple[str, ...]) -> None:
    """Refuse a hardware setting that is not a positive number (a zero divides, a negative
    distance turns a device round), naming it."""
    for name in names:
        value = getattr(spec, name)
        values = value if isinstance(value, (tuple, list)) else (value,)
        if not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in values
        ):
            raise ValueError(f"{part}.{name}: {value}; a positive number")


@dataclass(frozen=True)
class Projector:
    """One projector in the world frame."""

    name: str
    K: np.ndarray  # 3x3 intrinsics (projector pixels)
    R: np.ndarray  # 3x3 world -> projector rotation
    t: np.ndarray  # 3 translation (mm)
    width_px: int
    height_px: int
    phase_axis: str = "u"  # the pixel axis the fringe phase runs along

    @property
    def P(self) -> np.ndarray:
        """3x4 projection matrix: world mm -> homogeneous projector pixels."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def center(self) -> np.ndarray:
        """Centre of projection in world mm."""
        return -self.R.T @ self.t

    @property
    def axis(self) -> np.ndarray:
        """Unit optical axis (pointing out of the lens) in world coordinates."""
        return self.R[2].copy()

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) in mm -> projector pixel coordinates (..., 2)."""
        cam = points @ self.R.T + self.t
        uvw = cam @ self.K.T
        return uvw[..., :2] / uvw[..., 2:3]

    def in_image(self, uv: np.ndarray) -> np.ndarray:
        """Whether projector pixel coordinates (..., 2) fall on the projector's image."""
        u, v = uv[..., 0], uv[..., 1]
        return (u >= 0) & (u < self.width_px) & (v >= 0) & (v < self.height_px)

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Projector pixels (..., 2) -> (origin (3,), unit world directions (..., 3))."""
        ones = np.ones(uv.shape[:-1] + (1,))
        d_proj = np.concatenate([uv, ones], axis=-1) @ np.linalg.inv(self.K).T
        d = d_proj @ self.R  # R^T applied to row vectors
        return self.center, d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Camera:
    """The camera at one output resolution, in the world frame."""

    K: np.ndarray  # 3x3 intrinsics at (width_px, height_px)
    dist: np.ndarray  # k1, k2, p1, p2
    R: np.ndarray  # world -> camera rotation
    t: np.ndarray  # translation (mm)
    width_px: int
    height_px: int

    @property
    def P(self) -> np.ndarray:
        """3x4 projection matrix (pinhole part, before distortion): world mm -> pixels."""
        return self.K @ np.hstack([self.R, self.t[:, None]])

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    def distort(self, xy: np.ndarray) -> np.ndarray:
        """Brown-Conrady: ideal normalized coordinates (..., 2) -> distorted ones."""
        k1, k2, p1, p2 = self.dist
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert :meth:`distort` by fixed-point iteration (converges for realistic lenses)."""
        xy = xy_d.copy()
        for _ in range(iterations):
            xy = xy + (xy_d - self.distort(xy))
        return xy

    def pixel_rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (..., 2) -> (centre (3,), unit world directions (..., 3)).

        Distortion is inverted, so the rays are the ones that really land on those pixels.
        """
        xy_d = (uv - self.K[:2, 2]) / np.array([self.K[0, 0], self.K[1, 1]])
        xy = self.undistort(xy_d)
        d_cam = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        d = d_cam @ self.R
        return self.center, d / np.linalg.norm(d, axis=-1, keepdims=True)

    def centre_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """The rays through every pixel centre: (centre (3,), unit directions (H, W, 3))."""
        jj, ii = np.meshgrid(np.arange(self.width_px) + 0.5, np.arange(self.height_px) + 0.5)
        return self.pixel_rays(np.stack([jj, ii], -1))

    def project(self, points: np.ndarray, distorted: bool = True) -> np.ndarray:
        """World points (..., 3) -> pixel coordinates (..., 2)."""
        cam = points @ self.R.T + self.t
        xy = cam[..., :2] / cam[..., 2:3]
        if distorted:
            xy = self.distort(xy)
        return xy * np.array([self.K[0, 0], self.K[1, 1]]) + self.K[:2, 2]

    def depth(self, points: np.ndarray) -> np.ndarray:
        """Camera-axis z (mm) of world points (..., 3)."""
        return points @ self.R[2] + self.t[2]


def _look_at_rotation(center: np.ndarray, target: np.ndarray, right_hint: np.ndarray) -> np.ndarray:
    """World -> device rotation whose z axis points from ``center`` to ``target``."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = right_hint - (right_hint @ z) * z
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


@dataclass(frozen=True)
class Rig:
    """Camera plus four projectors; build with :meth:`at_resolution` for a given image size."""

    camera: CameraSpec = field(default_factory=CameraSpec)
    projector: ProjectorSpec = field(default_factory=ProjectorSpec)

    def camera_at(self, width_px: int, height_px: int | None = None) -> Camera:
        """Camera model for images of ``width_px`` x ``height_px`` covering the full sensor."""
        height_px = width_px if height_px is None else height_px
        spec = self.camera
        sw, sh = spec.sensor_mm
        fx = spec.focal_mm / sw * width_px
        fy = spec.focal_mm / sh * height_px
        K = np.array([[fx, 0.0, width_px / 2.0], [0.0, fy, height_px / 2.0], [0.0, 0.0, 1.0]])
        R = np.diag([1.0, -1.0, -1.0])  # camera looks down -z, image rows run along -y
        center = np.array([0.0, 0.0, spec.working_distance_mm])
        return Camera(K, np.asarray(spec.distortion, float), R, -R @ center, width_px, height_px)

    def projectors(self) -> dict[str, Projector]:
        """The four projectors in canonical order, keyed by view name."""
        spec = self.projector
        tilt = math.radians(spec.tilt_deg)
        fx = spec.width_px * spec.distance_mm / spec.field_mm[0]
        fy = spec.height_px * spec.distance_mm / spec.field_mm[1]
        K = np.array([[fx, 0, spec.width_px / 2], [0, fy, spec.height_px / 2], [0, 0, 1.0]])
        out = {}
        for name in VIEW_NAMES:
            ax, ay = _AZIMUTH_XY[name]
            azimuth = np.array([ax, ay, 0.0])
            center = spec.distance_mm * (math.sin(tilt) * azimuth + math.cos(tilt) * np.eye(3)[2])
            R = _look_at_rotation(center, np.zeros(3), right_hint=azimuth)
            out[name] = Projector(name, K, R, -R @ center, spec.width_px, spec.height_px)
        return out

    def to_dict(self) -> dict:
        return {"camera": asdict(self.camera), "projector": asdict(self.projector)}

    @classmethod
    def from_dict(cls, d: dict) -> Rig:
        cam = dict(d.get("camera", {}))
        proj = dict(d.get("projector", {}))
        for key in ("field_mm", "distortion"):
            if key in cam:
                cam[key] = tuple(cam[key])
        if "field_mm" in proj:
            proj["field_mm"] = tuple(proj["field_mm"])
        return cls(CameraSpec(**cam), ProjectorSpec(**proj))

    def geometry(self, width_px: int, height_px: int | None = None) -> dict:
        return rig_geometry(self, width_px, height_px)


def rig_geometry(rig, width_px: int, height_px: int | None = None) -> dict:
    """A rig's calibration (a :class:`Rig` or a calibration file's) at one resolution as plain
    JSON-able lists (stored in the manifest)."""
    cam = rig.camera_at(width_px, height_px)
    return {
        "camera": {
            "width_px": cam.width_px,
            "height_px": cam.height_px,
            "K": cam.K.tolist(),
            "dist_k1_k2_p1_p2": cam.dist.tolist(),
            "R_world_to_camera": cam.R.tolist(),
            "t_mm": cam.t.tolist(),
            "P": cam.P.tolist(),
        },
        "projectors": {
            name: {
                "width_px": p.width_px,
                "height_px": p.height_px,
                "K": p.K.tolist(),
                "R_world_to_projector": p.R.tolist(),
                "t_mm": p.t.tolist(),
                "P": p.P.tolist(),
                "phase_axis": p.phase_axis,
            }
            for name, p in rig.projectors().items()
        },
    }
