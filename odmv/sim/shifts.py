"""Shifts: the twin rendered through a rig, optics or surfaces that differ from the nominal ones.

A shifted dataset shows the same scenes as a nominal one, but its images come from a perturbed
rig while its manifest keeps the nominal calibration: what a user's calibration, made before the
rig drifted, says. The reference-phase input and the classical method therefore use the nominal
rig, as they would on the shop floor. Each shift has one strength; at its nominal strength it
renders the nominal images byte for byte.

- ``projector_rotation``: each projector turned about its centre by X deg, each about its own
  random axis (nominal 0);
- ``projector_shift``: each projector's centre moved X mm in its own random direction (0);
- ``camera_focal``: the camera's focal length +X % (0);
- ``gamma``: projector gamma X, uncompensated: the pattern is (A + B cos)^X (1);
- ``defocus``: Gaussian blur of the optical image, sigma X output px (0);
- ``ambient``: ambient light +X of full scale (0);
- ``noise``: photon and read noise X times their nominal std (1);
- ``exposure``: every irradiance times X, saturating above full scale (1);
- ``texture``: printed marks on the parts' albedo, contrast X: albedo times 1 - X on a mark (0);
- ``gloss``: a specular lobe lit by each projector, X of its irradiance at the peak (0);
- ``dead_view``: the projector named X gives no light, its images are ambient only (none).

The random axes and directions are drawn from ``seed`` per projector, the same for every scene.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from odmv.rig import VIEW_NAMES, Projector, Rig
from odmv.sim.render import RenderConfig

#: each shift's nominal strength (None for dead_view: no projector dead)
NOMINAL: dict[str, float | str | None] = {
    "none": None,
    "projector_rotation": 0.0,
    "projector_shift": 0.0,
    "camera_focal": 0.0,
    "gamma": 1.0,
    "defocus": 0.0,
    "ambient": 0.0,
    "noise": 1.0,
    "exposure": 1.0,
    "texture": 0.0,
    "gloss": 0.0,
    "dead_view": None,
}


GEOMETRIC = ("projector_rotation", "projector_shift", "camera_focal")  # they move the rig


class ShiftError(ValueError):
    """A one-line error about a shift's name or strength."""


@dataclass(frozen=True)
class Shift:
    name: str = "none"
    strength: float | str | None = None  # None: the shift's nominal strength
    seed: int = 0

    def __post_init__(self):
        if self.name not in NOMINAL:
            raise ShiftError(f"shift {self.name!r} unknown; choose from {', '.join(NOMINAL)}")
        if self.name == "dead_view":
            if self.strength is not None and self.strength not in VIEW_NAMES:
                raise ShiftError(
                    f"shift dead_view: strength {self.strength!r} is not a view; "
                    f"name one of {', '.join(VIEW_NAMES)}"
                )
            return
        if self.strength is None or self.name == "none":
            return
        try:
            value = float(self.strength)
        except (TypeError, ValueError):
            raise ShiftError(
                f"shift {self.name}: strength {self.strength!r} is not a number"
            ) from None
        if not math.isfinite(value) or (value <= 0 and self.name in ("gamma", "exposure")):
            raise ShiftError(f"shift {self.name}: strength {value} is out of range")
        if value < 0 and self.name != "camera_focal":
            raise ShiftError(f"shift {self.name}: strength {value} must not be negative")
        object.__setattr__(self, "strength", value)

    @property
    def value(self):
        """The strength in effect (the nominal one where none is given)."""
        return NOMINAL[self.name] if self.strength is None else self.strength

    @property
    def nominal(self) -> bool:
        return self.value == NOMINAL[self.name]

    def label(self) -> str:
        """``nominal``, or ``NAME:STRENGTH`` as :func:`parse_shift` reads it."""
        if self.nominal:
            return "nominal"
        value = f"{self.value:g}" if isinstance(self.value, float) else self.value
        return f"{self.name}:{value}"

    def to_dict(self) -> dict:
        return {"name": self.name, "strength": self.value, "seed": self.seed}

    # -------------------------------------------------------------------------- applied
    def rig(self, rig: Rig) -> Rig:
        """The rig that renders the images (the manifest keeps ``rig``)."""
        x = self.value
        if self.nominal or self.name not in GEOMETRIC:
            return rig
        if self.name == "camera_focal":  # (a moved-projector rig keeps its moves)
            focal = rig.camera.focal_mm * (1 + x / 100)
            return replace(rig, camera=replace(rig.camera, focal_length_mm=focal))
        if not isinstance(rig, MovedProjectorsRig):
            rig = MovedProjectorsRig(rig.camera, rig.projector, seed=self.seed)
        if self.name == "projector_rotation":
            return replace(rig, rotation_deg=x, seed=self.seed)
        return replace(rig, shift_mm=x, seed=self.seed)

    def render(self, cfg: RenderConfig) -> RenderConfig:
        """The optics and sensor that render the images."""
        x = self.value
        if self.nominal:
            return cfg
        if self.name == "gamma":
            return replace(cfg, projector_gamma=x)
        if self.name == "defocus":
            return replace(cfg, defocus_sigma_px=x)
        if self.name == "ambient":
            return replace(cfg, ambient=cfg.ambient + x)
        if self.name == "noise":
            return replace(cfg, read_noise=cfg.read_noise * x, full_well_e=cfg.full_well_e / x**2)
        if self.name == "exposure":
            return replace(
                cfg, ambient=cfg.ambient * x, projector_irradiance=cfg.projector_irradiance * x
            )
        return cfg

    @property
    def texture_contrast(self) -> float:
        return float(self.value) if self.name == "texture" else 0.0

    @property
    def gloss(self) -> float:
        return float(self.value) if self.name == "gloss" else 0.0

    @property
    def dead_view(self) -> str | None:
        return self.value if self.name == "dead_view" else None


NOMINAL_SHIFT = Shift()


@dataclass(frozen=True)
class Applied:
    """What a set of shifts does to a render: the rig and optics that render the images, the
    surfaces' texture and gloss, and the dead projector (odmv.sim.render.render_scene)."""

    rig: Rig
    render: RenderConfig
    texture: float = 0.0
    gloss: float = 0.0
    dead_view: str | None = None


def apply(shifts, rig: Rig, cfg: RenderConfig) -> Applied:
    """``shifts`` (one Shift or several, of distinct names) applied together to the nominal
    ``rig`` and ``cfg``."""
    shifts = [shifts] if isinstance(shifts, Shift) else list(shifts)
    names = [s.name for s in shifts if s.name != "none"]
    if len(set(names)) < len(names):
        raise ShiftError(f"shifts {names}: each shift at most once")
    out = Applied(rig, cfg)
    for s in shifts:
        out = replace(
            out,
            rig=s.rig(out.rig),
            render=s.render(out.render),
            texture=out.texture or s.texture_contrast,
            gloss=out.gloss or s.gloss,
            dead_view=out.dead_view or s.dead_view,
        )
    return out


def parse_shift(text: str, seed: int = 0) -> Shift:
    """``NAME:STRENGTH`` (or ``NAME`` for its nominal strength, ``none``) as a Shift."""
    name, _, strength = str(text).partition(":")
    return Shift(name, strength or None, seed)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def _axis_angle(axis: np.ndarray, deg: float) -> np.ndarray:
    """Rotation matrix (Rodrigues) about a unit axis."""
    a = math.radians(deg)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k


@dataclass(frozen=True)
class MovedProjectorsRig(Rig):
    """A rig whose projectors are turned about their centres (``rotation_deg``, each about its
    own random axis) or moved (``shift_mm``, each in its own random direction); the draws come
    from ``seed`` and the projector's name."""

    rotation_deg: float = 0.0
    shift_mm: float = 0.0
    seed: int = field(default=0)

    def projectors(self) -> dict[str, Projector]:
        out = {}
        for k, (name, p) in enumerate(super().projectors().items()):
            rng = np.random.default_rng([self.seed, k])
            axis, direction = _random_unit(rng), _random_unit(rng)
            R = p.R @ _axis_angle(axis, self.rotation_deg).T if self.rotation_deg else p.R
            centre = p.center + self.shift_mm * direction
            out[name] = replace(p, R=R, t=-R @ centre)
        return out
