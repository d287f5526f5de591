"""The dataset contract: ``manifest.json`` plus one folder per scene (see docs/dataset.md).

Everything that knows a file name inside a dataset asks this module, so the simulator, the
validator and the data module cannot drift apart.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from odmv.io.atomic import write_json
from odmv.io.calibration import CalibratedRig, CalibrationError, parse_calibration
from odmv.rig import VIEW_NAMES, Rig

FORMAT = "odmv-fpp-dataset"
#: ``quantity`` of a dataset whose depth.exr holds height above the reference plane.
HEIGHT_QUANTITY = "height above the reference plane, mm"
VERSION = 1
MANIFEST = "manifest.json"
SPLITS = ("train", "val", "test")
IMAGE_MODES = ("full", "training")

DEPTH_FILE = "depth.exr"  # channel "Z": camera-axis z in mm, finite everywhere
LIT_FILE = "lit.exr"  # one channel per view: 1 where that projector lights the pixel, else 0
# one channel per view: 1 where the pixel's surface point lies inside that projector's frustum
# (lit or not); optional: datasets without it get it from depth and the rig (odmv.data.subsets)
FOOTPRINT_FILE = "footprint.exr"
PROJ_COORD_FILE = "projector_coord.exr"  # one channel per view: projector px, NaN where unlit
SCENE_SPEC_FILE = "scene.json"  # what the scene was made of, enough to re-render it
FRINGE_DIR = "fringe"
FRINGE_CHANNEL = "Y"
DEPTH_CHANNEL = "Z"


class ManifestError(ValueError):
    """A one-line error naming the manifest and the problem."""


@dataclass(frozen=True)
class FringeSpec:
    """Phase-shifting sequence per projector.

    ``periods_px``: fringe period in projector pixels along the phase axis, one per frequency,
    lowest frequency first. ``steps``: phase steps per frequency (phase shift 2*pi*n/steps).
    ``uniform``: whether a flat full-intensity image follows the sequences. ``train_frequency``
    and ``train_step`` name the image a network sees by default (the paper: highest frequency,
    first step).
    """

    periods_px: tuple[float, ...] = (1920.0, 240.0, 30.0)
    steps: int = 12
    uniform: bool = True
    train_frequency: int = -1
    train_step: int = 0

    @property
    def highest(self) -> int:
        """Index of the highest-frequency (shortest-period) sequence."""
        return min(range(len(self.periods_px)), key=lambda i: self.periods_px[i])

    def resolve_frequency(self, index: int) -> int:
        n = len(self.periods_px)
        if not -n <= index < n:
            raise ManifestError(f"fringe frequency index {index} out of range for {n} frequencies")
        return index % n

    @property
    def images_per_view(self) -> int:
        return len(self.periods_px) * self.steps + int(self.uniform)


def fringe_name(view: str, frequency: int, step: int) -> str:
    """File name (inside ``fringe/``) of one phase-shifted image."""
    return f"{view}_f{frequency}_s{step:02d}.exr"


def uniform_name(view: str) -> str:
    return f"{view}_uniform.exr"


@dataclass
class Manifest:
    """Parsed ``manifest.json``."""

    root: Path
    height_px: int
    width_px: int
    views: tuple[str, ...]
    fringe: FringeSpec
    rig: Rig | CalibratedRig | None  # None: not known (an import without a calibration)
    images: str = "full"
    scenes: list[dict] = field(default_factory=list)
    version: int = VERSION
    extra: dict = field(default_factory=dict)

    @property
    def quantity(self) -> str:
        """What ``depth.exr`` holds: ``depth`` (camera-axis z, mm; the twin's, most imports')
        or ``height`` (above the reference plane, mm; e.g. the uhrnet format's)."""
        return "height" if self.extra.get("quantity") == HEIGHT_QUANTITY else "depth"

    def dark_views(self) -> set[str]:
        """Views rendered without their projector's light on purpose (a robustness shift's
        dead projector), whose images hold no fringe by design."""
        shift = self.extra.get("simulation", {}).get("shift") or {}
        return {shift["strength"]} if shift.get("name") == "dead_view" else set()

    def scene_dir(self, scene_id: str) -> Path:
        return self.root / "scenes" / scene_id

    def fringe_files(self, scene_id: str) -> list[Path]:
        """Every fringe image this manifest promises for one scene, in a fixed order."""
        d = self.scene_dir(scene_id) / FRINGE_DIR
        f = self.fringe
        if self.images == "training":
            fi = f.resolve_frequency(f.train_frequency)
            return [d / fringe_name(v, fi, f.train_step) for v in self.views]
        files = []
        for v in self.views:
            files += [
                d / fringe_name(v, fi, s) for fi in range(len(f.periods_px)) for s in range(f.steps)
            ]
            if f.uniform:
                files.append(d / uniform_name(v))
        return files

    def ground_truth_files(self, scene_id: str) -> list[Path]:
        d = self.scene_dir(scene_id)
        return [d / DEPTH_FILE, d / LIT_FILE, d / PROJ_COORD_FILE, d / SCENE_SPEC_FILE]

    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "version": self.version,
            "units": {
                "length": "mm",
                "depth": HEIGHT_QUANTITY if self.quantity == "height" else "camera-axis z in mm",
                "projector_coord": "projector pixels along each projector's phase_axis",
                "fringe": "linear relative irradiance (float32), 1 = white on a unit-albedo "
                "surface facing the projector at the reference distance",
            },
            "image_size": {"height_px": self.height_px, "width_px": self.width_px},
            "views": list(self.views),
            "fringe": asdict(self.fringe),
            "images": self.images,
            "rig": self._rig_entry(),
            "scenes": self.scenes,
            **self.extra,
        }

    def _rig_entry(self) -> dict | None:
        if self.rig is None:
            return None
        if isinstance(self.rig, CalibratedRig):
            entry = {"calibration": self.rig.source}
        else:
            entry = {"spec": self.rig.to_dict()}
        return entry | {"geometry": self.rig.geometry(self.width_px, self.height_px)}

    def write(self) -> Path:
        """Write ``manifest.json`` atomically."""
        return write_json(self.root / MANIFEST, self.to_json())


def _require(d: dict, key: str, kind: type | tuple, path: Path):
    if key not in d:
        raise ManifestError(f"{path}: missing key {key!r}")
    if not isinstance(d[key], kind):
        raise ManifestError(f"{path}: key {key!r} has the wrong type ({type(d[key]).__name__})")
    return d[key]


def _rig_of(entry, known: bool, path: Path) -> Rig | CalibratedRig | None:
    """The manifest's rig: the twin's (``spec``), a calibration file's (``calibration``), or
    None where it is not known (``null``, or an older import's placeholder: rig_known false)."""
    if entry is None or known is False:
        return None
    if not isinstance(entry, dict):
        raise ManifestError(f"{path}: key 'rig' has the wrong type ({type(entry).__name__})")
    if "calibration" in entry:
        try:
            return parse_calibration(entry["calibration"], f"{path}: rig.calibration")
        except CalibrationError as exc:
            raise ManifestError(str(exc)) from None
    try:
        return Rig.from_dict(entry.get("spec", {}))
    except TypeError as exc:
        raise ManifestError(f"{path}: bad rig specification ({exc})") from None
    except ValueError as exc:
        raise ManifestError(f"{path}: rig.spec.{exc}") from None


def _check_geometry(stored, derived: dict, path: Path, where: str = "rig.geometry") -> None:
    """The manifest's ``rig.geometry`` is written from its ``rig.spec`` (or calibration) for
    readers of the file; the project reads the spec. An edited geometry would be silently
    ignored, so one that differs from the spec's is refused, naming the first entry."""
    if stored is None:
        return
    if isinstance(derived, dict):
        if not isinstance(stored, dict):
            raise ManifestError(f"{path}: {where} should be an object")
        for key, value in derived.items():
            if key in stored:
                _check_geometry(stored[key], value, path, f"{where}.{key}")
        return
    if isinstance(derived, str):
        if stored != derived:
            raise ManifestError(f"{path}: {where} is {stored!r}, the rig gives {derived!r}")
        return
    try:
        same = np.allclose(
            np.asarray(stored, float), np.asarray(derived, float), rtol=1e-6, atol=1e-9
        )
    except (TypeError, ValueError):
        same = False
    if not same:
        raise ManifestError(
            f"{path}: {where} is {stored}, but the rig gives {derived}: the geometry is "
            "written from rig.spec (or rig.calibration) and never read; edit that instead"
        )


def load_manifest(root: str | os.PathLike) -> Manifest:
    """Read and check the structure of ``root/manifest.json`` (not the images)."""
    root = Path(root)
    path = root / MANIFEST
    if not path.is_file():
        raise ManifestError(f"{path}: no manifest (is {root} an odmv dataset folder?)")
    try:
        d = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(d, dict):
        raise ManifestError(f"{path}: top level must be a JSON object")
    if d.get("format") != FORMAT:
        raise ManifestError(f"{path}: format is {d.get('format')!r}, expected {FORMAT!r}")
    version = _require(d, "version", int, path)
    if version != VERSION:
        raise ManifestError(
            f"{path}: version {version} is not supported (this odmv reads {VERSION})"
        )
    size = _require(d, "image_size", dict, path)
    h, w = size.get("height_px"), size.get("width_px")
    if not (isinstance(h, int) and isinstance(w, int) and h > 0 and w > 0):
        raise ManifestError(f"{path}: image_size needs positive integer height_px and width_px")
    views = _require(d, "views", list, path)
    unknown = [v for v in views if v not in VIEW_NAMES]
    if unknown or not views or len(set(views)) != len(views):
        raise ManifestError(f"{path}: views {views} must be distinct names from {list(VIEW_NAMES)}")
    fr = _require(d, "fringe", dict, path)
    try:
        fringe = FringeSpec(
            periods_px=tuple(float(p) for p in fr["periods_px"]),
            steps=int(fr["steps"]),
            uniform=bool(fr.get("uniform", False)),
            train_frequency=int(fr.get("train_frequency", -1)),
            train_step=int(fr.get("train_step", 0)),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ManifestError(f"{path}: bad fringe specification ({exc!r})") from None
    if not fringe.periods_px or fringe.steps < 1 or not 0 <= fringe.train_step < fringe.steps:
        raise ManifestError(f"{path}: fringe needs periods, steps >= 1 and a valid train_step")
    fringe.resolve_frequency(fringe.train_frequency)
    images = d.get("images", "full")
    if images not in IMAGE_MODES:
        raise ManifestError(f"{path}: images is {images!r}, expected one of {IMAGE_MODES}")
    if "rig" not in d:
        raise ManifestError(f"{path}: missing key 'rig'")
    rig = _rig_of(d["rig"], d.get("rig_known", True), path)
    if rig is not None:
        _check_geometry(d["rig"].get("geometry"), rig.geometry(w, h), path)
    scenes = _require(d, "scenes", list, path)
    seen = set()
    for i, s in enumerate(scenes):
        if not isinstance(s, dict) or not isinstance(s.get("id"), str) or not s["id"]:
            raise ManifestError(f"{path}: scenes[{i}] needs a non-empty string 'id'")
        if s["id"] in seen:
            raise ManifestError(f"{path}: scene id {s['id']!r} appears twice")
        seen.add(s["id"])
        if s.get("split") is not None and s["split"] not in SPLITS:
            raise ManifestError(
                f"{path}: scene {s['id']!r} has split {s['split']!r}, not in {SPLITS}"
            )
    known = {
        "format",
        "version",
        "units",
        "image_size",
        "views",
        "fringe",
        "images",
        "rig",
        "scenes",
    }
    return Manifest(
        root=root,
        height_px=h,
        width_px=w,
        views=tuple(v for v in VIEW_NAMES if v in views),
        fringe=fringe,
        rig=rig,
        images=images,
        scenes=scenes,
        version=version,
        extra={k: v for k, v in d.items() if k not in known},
    )
