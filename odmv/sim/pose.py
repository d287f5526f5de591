"""Where a scene sits in the working volume: ``pose=fixed`` or ``pose=random``.

``fixed`` (the default, and the paper's twin): every scene stands on the base plane z = 0 under
the camera, so the background's depth is one constant (150 mm; the top of a pcb board 1.6 mm
above it) in every scene, and a net can recall it instead of measuring it.

``random``: each scene draws a pose from its own seed sequence ``[seed, index, 3]`` (the parts
are drawn as before from ``[seed, index]``, so a scene keeps its parts under any pose):

- the support's distance along the camera axis, uniform in +-``offset_mm`` (positive: farther
  from the camera). 8 mm is about 0.7 of the height one fringe order of the 64 px twin spans
  (about 11 mm), so a net cannot take the order from a remembered plane;
- its tilt about the world x and y axes, each uniform in +-``tilt_deg``; rotations are about
  the point where the camera axis meets the support, so the field's centre keeps its depth;
- a share ``unsupported`` of scenes has no flat support under its parts: half of the
  primitives and freeform scenes stand on a smooth freeform surface that fills the field
  (``surface_mm`` peak to valley at most), the other half, and every unsupported pcb scene,
  hang over a far background (``far_mm`` below the parts' base, with a tilt of its own; a pcb
  is then a board of random size in a fixture, its edges in view);
- pcb boards are ``board_mm`` thick (uniform in the range; the fixed twin's 1.6 mm otherwise).

Why these ranges: the camera sees 35.5 mm at 150 mm; every projector lights a 23 mm band of it
(65 % of the pixels on the nominal plane). Over +-8 mm and +-10 degrees each projector's share
stays within 0.61-0.66 (at 12 mm closer or farther it falls to 0.58), measured on the rig by
:func:`footprint_shares`. The twin models no depth of field (its optics are sharp at every
depth; ``render.defocus_sigma_px`` is one blur for the whole image), so the range is set by
the footprints and by the network's depth units: :func:`depth_range_mm` is the working volume
every pixel's depth lies in (the surface's valleys and a far background included), recorded in
the manifest as ``depth_range_mm`` so the data module maps it to the net's [-1, 1].
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

#: the tallest part any family draws stands at most this far above its support (mm)
TALLEST_PART_MM = 15.0
#: the support's corner that tilts farthest from the field's centre (mm, x and y): the field's
#: half width
FIELD_HALF_MM = 17.75
KINDS = ("fixed", "random")
SUPPORTS = ("plane", "surface", "far")


class PoseError(ValueError):
    """A one-line error about the pose settings."""


@dataclass(frozen=True)
class PoseSettings:
    """How scenes are placed (the module docstring); ``kind=fixed`` ignores the ranges."""

    kind: str = "fixed"
    offset_mm: float = 8.0
    tilt_deg: float = 10.0
    unsupported: float = 0.2
    far_mm: tuple[float, float] = (3.0, 6.0)
    surface_mm: float = 2.5
    board_mm: tuple[float, float] = (0.8, 3.2)

    def __post_init__(self):
        if self.kind not in KINDS:
            raise PoseError(f"pose.kind: {self.kind!r}; choose {' or '.join(KINDS)}")
        lo, hi = self.far_mm
        blo, bhi = self.board_mm
        checks = {
            "offset_mm": 0 <= self.offset_mm <= 12,
            "tilt_deg": 0 <= self.tilt_deg <= 15,
            "unsupported": 0 <= self.unsupported <= 1,
            "far_mm": 0 < lo <= hi and hi < 2 * self.offset_mm + 1e-9 or self.unsupported == 0,
            "surface_mm": 0 <= self.surface_mm <= 5,
            "board_mm": 0.4 <= blo <= bhi <= 4,
        }
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise PoseError(
                f"pose.{bad[0]}: {getattr(self, bad[0])} is outside what the twin keeps inside "
                "the projectors' footprints (offset_mm 0-12, tilt_deg 0-15, unsupported 0-1, "
                "far_mm low <= high < 2 * offset_mm, surface_mm 0-5, board_mm 0.4-4)"
            )

    @classmethod
    def from_dict(cls, d: dict | None) -> PoseSettings:
        d = dict(d or {})
        for key in ("far_mm", "board_mm"):
            if key in d:
                d[key] = tuple(float(x) for x in d[key])
        try:
            return cls(**d)
        except TypeError as e:
            raise PoseError(f"pose: {e}") from None

    @property
    def fixed(self) -> bool:
        return self.kind == "fixed"

    def to_dict(self) -> dict:
        return asdict(self) | {"far_mm": list(self.far_mm), "board_mm": list(self.board_mm)}

    def depth_range_mm(self, working_distance_mm: float) -> tuple[float, float]:
        """The working volume (camera-axis depth, mm) every pixel of a scene lies in."""
        reach = FIELD_HALF_MM * 2 * math.tan(math.radians(self.tilt_deg))
        near = working_distance_mm - self.offset_mm - reach - TALLEST_PART_MM - self.surface_mm
        far = working_distance_mm + self.offset_mm + reach + self.surface_mm
        return near, far

    def draw(self, seed: int, index: int, family: str) -> dict | None:
        """Scene ``index``'s pose (None for ``fixed``): ``support``, ``offset_mm`` and
        ``tilt_deg`` [about x, about y] of the parts' support, the ``ground``'s own pose, and
        ``board_mm`` (pcb) or ``surface`` waves (a freeform support) where they apply."""
        if self.fixed:
            return None
        rng = np.random.default_rng([seed, index, 3])
        support = "plane"
        if rng.random() < self.unsupported:
            support = "far" if family == "pcb" or rng.random() < 0.5 else "surface"
        off = self.offset_mm
        if support == "far":  # the background, not the parts, keeps to +-offset_mm
            offset = float(rng.uniform(-off, off - self.far_mm[1]))
        else:
            offset = float(rng.uniform(-off, off))
        tilt = rng.uniform(-self.tilt_deg, self.tilt_deg, 2).tolist()
        pose = {"support": support, "offset_mm": offset, "tilt_deg": tilt}
        if support == "far":
            below = float(rng.uniform(*self.far_mm))
            own = rng.uniform(-self.tilt_deg, self.tilt_deg, 2).tolist()
            pose["ground"] = {"offset_mm": offset + below, "tilt_deg": own}
        else:
            pose["ground"] = {"offset_mm": offset, "tilt_deg": tilt}
        if family == "pcb":
            pose["board_mm"] = float(rng.uniform(*self.board_mm))
            if support == "far":  # a board in a fixture: its edges in view
                pose["board_half_mm"] = float(rng.uniform(14.5, 17.0))
        if support == "surface":
            pose["surface"] = surface_waves(rng, self.surface_mm)
        return pose


def surface_waves(rng: np.random.Generator, peak_to_valley_mm: float) -> list[list[float]]:
    """A smooth freeform height field as waves [amplitude mm, kx, ky (rad / mm), phase]:
    wavelengths 20-60 mm, amplitudes summing to at most half ``peak_to_valley_mm``."""
    n = int(rng.integers(2, 5))
    amp = rng.dirichlet(np.ones(n)) * peak_to_valley_mm / 2 * rng.uniform(0.5, 1.0)
    k = 2 * math.pi / rng.uniform(20.0, 60.0, n)
    angle = rng.uniform(0, 2 * math.pi, n)
    phase = rng.uniform(0, 2 * math.pi, n)
    return np.c_[amp, k * np.cos(angle), k * np.sin(angle), phase].tolist()


def surface_height(waves, x, y):
    """The freeform support's height (mm) at world (x, y) mm."""
    w = np.asarray(waves, float).reshape(-1, 4)
    x, y = np.asarray(x, float), np.asarray(y, float)
    return sum(a * np.sin(kx * x + ky * y + c) for a, kx, ky, c in w)


def rotation(tilt_deg) -> np.ndarray:
    """3 x 3: a tilt by ``tilt_deg[0]`` about the world x axis, then ``tilt_deg[1]`` about y."""
    rx, ry = (math.radians(float(a)) for a in tilt_deg)
    cx, sx, cy, sy = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    return my @ mx


def place(points: np.ndarray, offset_mm: float, tilt_deg) -> np.ndarray:
    """World points (..., 3) of a support at z = 0 tilted about the origin, then moved
    ``offset_mm`` along the camera axis away from the camera (world -z)."""
    return points @ rotation(tilt_deg).T - np.array([0.0, 0.0, offset_mm])


def footprint_shares(rig, pose: dict | None, size_px: int = 64) -> dict[str, float]:
    """Each projector's share of the camera pixels whose ray meets the support plane of
    ``pose`` inside that projector's footprint (how the ranges above were chosen)."""
    p = pose or {"offset_mm": 0.0, "tilt_deg": [0.0, 0.0]}
    cam = rig.camera_at(size_px)
    origin, d = cam.centre_rays()
    normal = rotation(p["tilt_deg"]) @ np.array([0.0, 0.0, 1.0])
    point = np.array([0.0, 0.0, -p["offset_mm"]])
    t = ((point - origin) @ normal) / (d @ normal)
    pts = origin + t[..., None] * d
    return {k: float(pr.in_image(pr.project(pts)).mean()) for k, pr in rig.projectors().items()}
