"""Procedural scene families and mesh loading for the digital twin.

A scene is described by a JSON-able *spec* (a list of parts, each a shape with its size, pose
and albedo); :func:`build_scene` turns a spec into one triangle soup. Specs are drawn from a
seeded generator per scene, so the same (seed, index) always gives the same scene, and the spec
stored beside the images re-renders it exactly.

Lengths are mm in the rig's world frame: a spec is drawn on the base plane z = 0, objects
stand on it, the camera field is about 35.5 mm square around the origin. A spec's ``pose``
(odmv.sim.pose; absent: the fixed twin) then places the support and the ground in the working
volume, and a ``move`` (the prior probe's) moves the whole scene after that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from odmv.sim.pose import place, surface_height

FAMILIES = ("primitives", "pcb", "freeform")
MESH_SUFFIXES = (".stl", ".obj", ".ply")

# Half-width (mm) of the area where objects are placed; the camera sees +-17.7 mm.
PLACE_HALF_MM = 14.0
# The ground plane reaches well past the field so every camera ray hits something.
GROUND_HALF_MM = 60.0


class SceneError(ValueError):
    """A one-line error about a scene or a mesh file."""


@dataclass
class Scene:
    """Triangles (F x 3 x 3, mm) with one albedo per triangle."""

    triangles: np.ndarray
    albedo: np.ndarray

    @property
    def n_faces(self) -> int:
        return len(self.triangles)


# ----------------------------------------------------------------------------- shapes
def _rotation(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    rx, ry, rz = (math.radians(a) for a in (rx_deg, ry_deg, rz_deg))
    m = trimesh.transformations.euler_matrix(rx, ry, rz, "sxyz")
    return m[:3, :3]


def _shape_mesh(part: dict, mesh_cache: dict) -> trimesh.Trimesh:
    kind = part["shape"]
    s = part.get("size", [])
    if kind == "box":
        return trimesh.creation.box(extents=s)
    if kind == "cylinder":
        return trimesh.creation.cylinder(radius=s[0], height=s[1], sections=48)
    if kind == "cone":
        return trimesh.creation.cone(radius=s[0], height=s[1], sections=48)
    if kind == "sphere":
        return trimesh.creation.icosphere(subdivisions=4, radius=s[0])
    if kind == "capsule":
        return trimesh.creation.capsule(radius=s[0], height=s[1], count=[24, 24])
    if kind == "torus":
        return trimesh.creation.torus(
            major_radius=s[0], minor_radius=s[1], major_sections=48, minor_sections=24
        )
    if kind == "blob":
        return _blob(part["coeffs"])
    if kind == "superquadric":
        return _superquadric(*s)
    if kind == "file":
        return load_mesh(Path(part["path"]), mesh_cache).copy()
    raise SceneError(f"unknown shape {kind!r}")


def _blob(coeffs: list[list[float]]) -> trimesh.Trimesh:
    """Unit sphere displaced radially by a sum of smooth 3D waves: r = 1 + sum a sin(k.p + c)."""
    m = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    p = m.vertices
    c = np.asarray(coeffs, float)  # rows: amplitude, kx, ky, kz, phase
    r = 1.0 + (c[:, 0] * np.sin(p @ c[:, 1:4].T + c[:, 4])).sum(1)
    return trimesh.Trimesh(p * r[:, None], m.faces, process=False)


def _superquadric(a: float, b: float, c: float, e1: float, e2: float, n: int = 48):
    """Closed superquadric surface with semi-axes a, b, c and shape exponents e1, e2."""

    def spow(x, e):
        return np.sign(x) * np.abs(x) ** e

    eta = np.linspace(-math.pi / 2, math.pi / 2, n)[1:-1]
    omega = np.linspace(-math.pi, math.pi, 2 * n, endpoint=False)
    E, O = np.meshgrid(eta, omega, indexing="ij")
    x = a * spow(np.cos(E), e1) * spow(np.cos(O), e2)
    y = b * spow(np.cos(E), e1) * spow(np.sin(O), e2)
    z = c * spow(np.sin(E), e1)
    verts = np.c_[x.ravel(), y.ravel(), z.ravel()]
    rows, cols = E.shape
    idx = np.arange(rows * cols).reshape(rows, cols)
    nxt = np.roll(idx, -1, axis=1)
    quads_a = np.stack([idx[:-1], nxt[:-1], nxt[1:]], -1).reshape(-1, 3)
    quads_b = np.stack([idx[:-1], nxt[1:], idx[1:]], -1).reshape(-1, 3)
    south, north = len(verts), len(verts) + 1
    verts = np.vstack([verts, [0, 0, -c], [0, 0, c]])
    cap_s = np.stack([np.full(cols, south), nxt[0], idx[0]], -1)
    cap_n = np.stack([np.full(cols, north), idx[-1], nxt[-1]], -1)
    faces = np.vstack([quads_a, quads_b, cap_s, cap_n])
    mesh = trimesh.Trimesh(verts, faces, process=False)
    return mesh


def load_mesh(path: Path, cache: dict | None = None) -> trimesh.Trimesh:
    """Load an STL/OBJ/PLY file as one triangle mesh; a one-line SceneError if it cannot be."""
    key = str(path)
    if cache is not None and key in cache:
        return cache[key]
    if not path.is_file():
        raise SceneError(f"{path}: mesh file not found")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:
        detail = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SceneError(f"{path}: cannot read mesh ({detail})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise SceneError(f"{path}: cannot read mesh (no triangles found)")
    if not np.isfinite(mesh.vertices).all():
        raise SceneError(f"{path}: cannot read mesh (non-finite vertex coordinates)")
    if cache is not None:
        cache[key] = mesh
    return mesh


def build_scene(spec: dict, mesh_cache: dict | None = None) -> Scene:
    """Triangles and albedos of a scene spec. Parts are placed by ``scale``, ``rotation_deg``
    (xyz Euler, applied about the shape's own centre) and ``position`` (of that centre)."""
    mesh_cache = {} if mesh_cache is None else mesh_cache
    tris, alb = [], []
    g = spec.get("ground", {"albedo": 0.5})
    pose = spec.get("pose")
    ground = _ground(pose)
    if pose is not None:
        ground = place(ground, pose["ground"]["offset_mm"], pose["ground"]["tilt_deg"])
    tris.append(ground)
    alb.append(np.full(len(ground), g["albedo"]))
    for part in spec["parts"]:
        m = _shape_mesh(part, mesh_cache)
        v = np.asarray(m.vertices, float)
        if part["shape"] == "file":
            v = v - (v.min(0) + v.max(0)) / 2
        v = v * np.asarray(part.get("scale", 1.0), float)
        v = v @ _rotation(*part.get("rotation_deg", (0, 0, 0))).T + np.asarray(part["position"])
        if pose is not None:
            v = place(v, pose["offset_mm"], pose["tilt_deg"])
        tris.append(v[np.asarray(m.faces)])
        alb.append(np.full(len(m.faces), part["albedo"]))
    triangles = np.concatenate(tris).astype(np.float64)
    if move := spec.get("move"):
        triangles = place(triangles, move["offset_mm"], move["tilt_deg"])
    return Scene(triangles, np.concatenate(alb).astype(np.float64))


#: the freeform support's grid step (mm): a third of a camera pixel at 480 px is 0.025 mm, but
#: its waves are 20 mm long or more, so 0.5 mm facets deviate from them by under 2 um
SURFACE_STEP_MM = 0.5


def _ground(pose: dict | None) -> np.ndarray:
    """The ground's triangles (F x 3 x 3, mm) before its pose: the plane z = 0, or the freeform
    support's height field where the pose has one."""
    h = GROUND_HALF_MM
    if pose is None or "surface" not in pose:
        return np.array(
            [[[-h, -h, 0], [h, -h, 0], [h, h, 0]], [[-h, -h, 0], [h, h, 0], [-h, h, 0]]], float
        )
    n = int(round(2 * h / SURFACE_STEP_MM)) + 1
    xs = np.linspace(-h, h, n)
    x, y = np.meshgrid(xs, xs)
    v = np.stack([x, y, surface_height(pose["surface"], x, y)], -1)
    a, b, c, d = v[:-1, :-1], v[:-1, 1:], v[1:, 1:], v[1:, :-1]
    return np.concatenate([np.stack([a, b, c], -2), np.stack([a, c, d], -2)]).reshape(-1, 3, 3)


# ----------------------------------------------------------------------------- families
def _free_spot(rng, taken: list, half_w: float, half_d: float, limit=PLACE_HALF_MM, tries=40):
    """An (x, y) whose axis-aligned footprint does not overlap ``taken`` (with 0.3 mm gap)."""
    for _ in range(tries):
        x = rng.uniform(-limit + half_w, limit - half_w)
        y = rng.uniform(-limit + half_d, limit - half_d)
        if all(
            abs(x - tx) > half_w + tw + 0.3 or abs(y - ty) > half_d + td + 0.3
            for tx, ty, tw, td in taken
        ):
            taken.append((x, y, half_w, half_d))
            return x, y
    return None


def _primitive(rng) -> dict:
    kind = rng.choice(["box", "cylinder", "sphere", "cone", "torus", "capsule"])
    albedo = float(rng.uniform(0.3, 0.9))
    if kind == "box":
        size = rng.uniform([2, 2, 1], [9, 9, 10]).tolist()
        base = size[2] / 2
    elif kind in ("cylinder", "cone"):
        size = [float(rng.uniform(1, 4.5)), float(rng.uniform(1.5, 10))]
        base = size[1] / 2
    elif kind == "sphere":
        size = [float(rng.uniform(1.5, 5))]
        base = size[0] * 0.7  # partly sunk into the plane, like a dome
    elif kind == "capsule":
        size = [float(rng.uniform(1, 3)), float(rng.uniform(2, 7))]
        base = size[0]
    else:
        major, minor = float(rng.uniform(2.5, 5)), float(rng.uniform(0.6, 1.5))
        size = [major, minor]
        base = minor
    # upright shapes keep a flat pose; a quarter are tipped over for varied silhouettes
    tilt = (
        [0.0, 0.0]
        if kind in ("sphere", "torus") or rng.random() < 0.75
        else rng.uniform(-25, 25, 2).tolist()
    )
    if kind == "capsule" and rng.random() < 0.5:
        tilt = [90.0, 0.0]  # lying down
        base = size[0]
    return {
        "shape": kind,
        "size": size,
        "rotation_deg": tilt + [float(rng.uniform(0, 360))],
        "albedo": albedo,
        "_base": base,
    }


def primitives_spec(rng, n_objects: tuple[int, int] = (2, 6)) -> dict:
    parts, taken = [], []
    for _ in range(int(rng.integers(n_objects[0], n_objects[1] + 1))):
        p = _primitive(rng)
        reach = max(p["size"][:2]) if p["shape"] == "box" else max(p["size"]) + 0.5
        spot = _free_spot(rng, taken, reach * 0.75, reach * 0.75)
        if spot is None:
            continue
        p["position"] = [spot[0], spot[1], p.pop("_base")]
        parts.append(p)
    return {
        "family": "primitives",
        "ground": {"albedo": float(rng.uniform(0.3, 0.7))},
        "parts": parts,
    }


# Real package bodies (length, width, height) in mm.
CHIP_SIZES = {
    "0402": (1.0, 0.5, 0.35),
    "0603": (1.6, 0.8, 0.45),
    "0805": (2.0, 1.25, 0.5),
    "1206": (3.2, 1.6, 0.55),
}
IC_BODIES = {
    "SOIC-8": (4.9, 3.9, 1.5),
    "SOIC-16": (9.9, 3.9, 1.5),
    "QFN-16": (3.0, 3.0, 0.9),
    "QFN-32": (5.0, 5.0, 0.9),
    "QFP-44": (10.0, 10.0, 1.4),
    "QFP-32": (7.0, 7.0, 1.4),
}
BOARD_MM = 1.6


def _box(size, pos, albedo, rz=0.0) -> dict:
    return {
        "shape": "box",
        "size": list(size),
        "position": list(pos),
        "rotation_deg": [0, 0, rz],
        "albedo": albedo,
    }


def _pcb_part(rng, top: float, taken: list) -> list[dict]:
    """One component on a board whose surface is at z = ``top``."""
    r = rng.random()
    if r < 0.35:  # chip resistor/capacitor: ceramic body with metal end caps
        code = rng.choice(list(CHIP_SIZES))
        length, width, height = CHIP_SIZES[code]
        rot = bool(rng.random() < 0.5)
        hw, hd = (width / 2, length / 2) if rot else (length / 2, width / 2)
        spot = _free_spot(rng, taken, hw, hd)
        if spot is None:
            return []
        return [
            _box(
                (length, width, height),
                (*spot, top + height / 2),
                float(rng.uniform(0.2, 0.6)),
                90.0 if rot else 0.0,
            )
        ]
    if r < 0.6:  # IC body with gull-wing / pad leads
        name = rng.choice(list(IC_BODIES))
        length, width, height = IC_BODIES[name]
        spot = _free_spot(rng, taken, length / 2 + 1.0, width / 2 + 1.0)
        if spot is None:
            return []
        x, y = spot
        parts = [_box((length, width, height), (x, y, top + height / 2), 0.12)]
        if not name.startswith("QFN"):
            n = max(2, int(length / 1.27))
            for i in range(n):
                lx = x - length / 2 + (i + 0.5) * length / n
                for sign in (-1, 1):
                    parts.append(
                        _box(
                            (0.45, 1.0, 0.25), (lx, y + sign * (width / 2 + 0.5), top + 0.125), 0.85
                        )
                    )
        return parts
    if r < 0.78:  # electrolytic capacitor: the tall shadow casters
        d = float(rng.choice([5.0, 6.3, 8.0, 10.0]))
        h = float(min(11.0, d * rng.uniform(1.05, 1.4)))
        spot = _free_spot(rng, taken, d / 2, d / 2)
        if spot is None:
            return []
        return [
            {
                "shape": "cylinder",
                "size": [d / 2, h],
                "position": [*spot, top + h / 2],
                "rotation_deg": [0, 0, 0],
                "albedo": float(rng.uniform(0.15, 0.5)),
            }
        ]
    if r < 0.9:  # 2.54 mm pin header: plastic base plus ~8.5 mm tall square pins
        pins = int(rng.integers(2, 7))
        rows = int(rng.integers(1, 3))
        length, width = pins * 2.54, rows * 2.54
        spot = _free_spot(rng, taken, length / 2, width / 2)
        if spot is None:
            return []
        x, y = spot
        parts = [_box((length, width, 2.5), (x, y, top + 1.25), 0.1)]
        for i in range(pins):
            for j in range(rows):
                px = x - length / 2 + (i + 0.5) * 2.54
                py = y - width / 2 + (j + 0.5) * 2.54
                parts.append(_box((0.64, 0.64, 8.5), (px, py, top + 4.25), 0.8))
        return parts
    # connector housing (JST/Molex-like box)
    length, width, height = rng.uniform([5, 4, 4], [12, 6, 7])
    spot = _free_spot(rng, taken, length / 2, width / 2)
    if spot is None:
        return []
    return [_box((length, width, height), (*spot, top + height / 2), float(rng.uniform(0.5, 0.9)))]


def pcb_spec(
    rng,
    n_parts: tuple[int, int] = (6, 18),
    board_mm: float = BOARD_MM,
    half_mm: float | None = None,
) -> dict:
    """A board ``board_mm`` thick, ``2 * half_mm`` square (None: past the field) with parts."""
    board_albedo = float(rng.uniform(0.2, 0.45))
    side = 2 * GROUND_HALF_MM * 0.9 if half_mm is None else 2 * half_mm
    parts = [_box((side, side, board_mm), (0, 0, board_mm / 2), board_albedo)]
    taken: list = []
    for _ in range(int(rng.integers(n_parts[0], n_parts[1] + 1))):
        parts += _pcb_part(rng, board_mm, taken)
    return {"family": "pcb", "ground": {"albedo": 0.5}, "parts": parts}


def freeform_spec(rng, mesh_files: list[Path] = (), n_objects: tuple[int, int] = (1, 3)) -> dict:
    parts, taken = [], []
    for _ in range(int(rng.integers(n_objects[0], n_objects[1] + 1))):
        albedo = float(rng.uniform(0.3, 0.9))
        rz = float(rng.uniform(0, 360))
        choice = rng.random()
        if mesh_files and choice < 0.5:
            path = mesh_files[int(rng.integers(len(mesh_files)))]
            extent = float(rng.uniform(6, 14))
            spot = _free_spot(rng, taken, extent / 2, extent / 2)
            if spot is None:
                continue
            parts.append(
                {
                    "shape": "file",
                    "path": str(path),
                    "target_extent_mm": extent,
                    "rotation_deg": [0, 0, rz],
                    "position": [*spot, 0.0],
                    "albedo": albedo,
                }
            )
        elif choice < 0.75:
            radius = float(rng.uniform(2.5, 5.5))
            waves = int(rng.integers(3, 7))
            coeffs = np.c_[
                rng.uniform(0.03, 0.12, waves),
                rng.normal(0, 2.5, (waves, 3)),
                rng.uniform(0, 2 * math.pi, waves),
            ]
            spot = _free_spot(rng, taken, radius * 1.4, radius * 1.4)
            if spot is None:
                continue
            flat = float(rng.uniform(0.4, 1.0))  # squash into a lens-like blob sometimes
            parts.append(
                {
                    "shape": "blob",
                    "coeffs": coeffs.tolist(),
                    "scale": [radius, radius, radius * flat],
                    "rotation_deg": [0, 0, rz],
                    "position": [*spot, radius * flat * 0.6],
                    "albedo": albedo,
                }
            )
        else:
            a, b, c = rng.uniform([2, 2, 1.5], [5.5, 5.5, 6])
            e1, e2 = rng.uniform([0.2, 0.2], [1.5, 1.5])
            spot = _free_spot(rng, taken, max(a, b), max(a, b))
            if spot is None:
                continue
            parts.append(
                {
                    "shape": "superquadric",
                    "size": [a, b, c, e1, e2],
                    "rotation_deg": [0, 0, rz],
                    "position": [*spot, c * 0.8],
                    "albedo": albedo,
                }
            )
    return {
        "family": "freeform",
        "ground": {"albedo": float(rng.uniform(0.3, 0.7))},
        "parts": parts,
    }


def mesh_files_in(folder: str | Path | None) -> list[Path]:
    """Every STL/OBJ/PLY file under ``folder`` (sorted, so scene draws are reproducible)."""
    if not folder:
        return []
    folder = Path(folder)
    if not folder.is_dir():
        raise SceneError(f"{folder}: mesh folder not found")
    return sorted(p for p in folder.rglob("*") if p.suffix.lower() in MESH_SUFFIXES)


def fit_file_parts(spec: dict, cache: dict) -> dict:
    """Turn each file part's ``target_extent_mm`` into an explicit scale and base height.

    Done once when the spec is drawn (it needs the mesh), so the stored spec is self-contained.
    """
    for part in spec["parts"]:
        if part["shape"] != "file" or "scale" in part:
            continue
        mesh = load_mesh(Path(part["path"]), cache)
        ext = mesh.extents
        s = part.pop("target_extent_mm") / float(ext[:2].max())
        s = min(s, 12.0 / float(ext[2]))  # keep parts under 12 mm tall
        part["scale"] = s
        part["position"][2] = float(ext[2]) * s / 2
    return spec


def draw_spec(
    family: str,
    rng: np.random.Generator,
    mesh_files: list[Path] = (),
    cache: dict | None = None,
    pose: dict | None = None,
) -> dict:
    """Draw one scene spec of ``family`` (``primitives``, ``pcb`` or ``freeform``), placed by
    ``pose`` (odmv.sim.pose; None: on the fixed twin's base plane)."""
    pose = pose or {}
    if family == "primitives":
        spec = primitives_spec(rng)
    elif family == "pcb":
        spec = pcb_spec(
            rng, board_mm=pose.get("board_mm", BOARD_MM), half_mm=pose.get("board_half_mm")
        )
    elif family == "freeform":
        spec = fit_file_parts(freeform_spec(rng, mesh_files), {} if cache is None else cache)
    else:
        raise SceneError(f"unknown scene family {family!r}; choose from {FAMILIES} or 'mix'")
    if pose:
        spec["pose"] = pose
        if "surface" in pose:
            _rest_on_surface(spec["parts"], pose["surface"])
    return spec


def _rest_on_surface(parts: list[dict], waves) -> None:
    """Lower or raise each part by the freeform support's lowest height under its footprint
    (centre and four points at its reach), so that it stands on the surface, not above it."""
    for part in parts:
        x, y = part["position"][:2]
        size = np.atleast_1d(np.asarray(part.get("size", [3.0]), float))
        r = float(size[:2].max()) / 2 if part["shape"] == "box" else float(size[0])
        xs = np.array([x, x + r, x - r, x, x])
        ys = np.array([y, y, y, y + r, y - r])
        part["position"][2] += float(np.min(surface_height(waves, xs, ys)))


def choose_family(family: str, proportions: dict[str, float], rng) -> str:
    """Resolve ``mix`` to one family by the configured proportions."""
    if family != "mix":
        return family
    names = [f for f in FAMILIES if proportions.get(f, 0) > 0]
    if not names:
        raise SceneError(f"mix proportions {proportions} give no family a positive share")
    w = np.array([proportions[f] for f in names], float)
    return names[int(rng.choice(len(names), p=w / w.sum()))]
