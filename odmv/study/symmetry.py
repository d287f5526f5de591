"""How exact the rig's quarter-turn symmetry is (the premise of ``data.augment=rot90``).

    python -m odmv.study symmetry data/synthetic-200x64px-4609dd24 --scenes 12

Renders stored scenes of a synthetic dataset again, noise-free, with the dataset's rig and
fringes, once as they are and once turned by +90 degrees about the camera axis, and compares
the turned scene's images with the original images turned (``odmv.data.augment``: view ``v``'s
role passes to ``NEXT[v]``). Prints, per scene, the largest differences in depth (mm), in any
fringe image (full-scale intensity, 1 = saturation) and in the lit masks (share of pixels):
with the dataset's lens, and with its tangential distortion terms set to zero.
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from odmv.data.augment import NEXT
from odmv.io.manifest import ManifestError, load_manifest
from odmv.sim.render import RenderConfig, render_scene
from odmv.sim.scenes import Scene, build_scene
from odmv.sim.writer import SCENE_SPEC_FILE, render_config, scene_record

TURN = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90 deg about z


def differences(scene: Scene, rig, m, cfg: RenderConfig) -> tuple[float, float, float]:
    """Largest |difference| of depth (mm), fringe intensity, and the lit masks' mismatch."""
    turned = Scene(scene.triangles @ TURN.T, scene.albedo)
    a, b = (
        render_scene(s, rig, m.height_px, m.width_px, m.fringe, m.views, cfg,
                     np.random.default_rng(0), m.images)
        for s in (scene, turned)
    )  # fmt: skip
    depth = float(np.abs(b.depth_mm - np.rot90(a.depth_mm)).max())
    fringe = max(
        float(np.abs(b.fringes[f"{NEXT[name.split('_', 1)[0]]}_{name.split('_', 1)[1]}"]
                     - np.rot90(img)).max())
        for name, img in a.fringes.items()
    )  # fmt: skip
    lit = max(float(np.mean(b.lit[NEXT[v]] != np.rot90(a.lit[v]))) for v in a.lit)
    return depth, fringe, lit


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("root", help="a dataset folder written by odmv.simulate")
    ap.add_argument(
        "--scenes", type=int, default=12, help="how many of its scenes (from the first)"
    )
    args = ap.parse_args(argv)
    try:
        m = load_manifest(args.root)
    except ManifestError as e:
        raise SystemExit(f"error: {e}") from None
    if set(NEXT) - set(m.views) or m.height_px != m.width_px:
        raise SystemExit(f"error: {args.root}: needs square images of all four views")
    cfg = dataclasses.replace(render_config(m), full_well_e=0.0, read_noise=0.0)
    k1, k2, _, _ = m.rig.camera.distortion
    lens = dataclasses.replace(m.rig.camera, distortion=(k1, k2, 0.0, 0.0))
    radial = dataclasses.replace(m.rig, camera=lens)
    print(
        "| scene | family | depth (mm) | fringe | lit (%) "
        "| without tangential terms: depth (mm) | fringe | lit (%) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for s in m.scenes[: args.scenes]:
        try:
            spec = scene_record(m, s["id"])["spec"]
        except (OSError, ValueError, KeyError) as e:
            path = m.scene_dir(s["id"]) / SCENE_SPEC_FILE
            raise SystemExit(f"error: {path}: not a scene record ({e})") from None
        scene = build_scene(spec)
        cells = []
        for rig in (m.rig, radial):
            d, f, lit = differences(scene, rig, m, cfg)
            cells += [f"{d:.1e}", f"{f:.1e}", f"{lit * 100:.2f}"]
        print(f"| {s['id']} | {s.get('family', '')} | " + " | ".join(cells) + " |")
