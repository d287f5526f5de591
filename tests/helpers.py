"""Small helpers shared by test modules (pytest puts tests/ on sys.path)."""

import numpy as np

from odmv.io.manifest import FringeSpec
from odmv.rig import VIEW_NAMES, Rig
from odmv.sim.render import RenderConfig, render_scene
from odmv.sim.scenes import build_scene

RIG = Rig()
CLEAN = RenderConfig(full_well_e=0.0, read_noise=0.0)  # noise-free
FRINGE = FringeSpec()


def render(parts, size, images="training", cfg=CLEAN):
    """Render ``parts`` on the base plane with the default rig, all four views, size x size."""
    scene = build_scene({"parts": parts})
    return render_scene(
        scene, RIG, size, size, FRINGE, VIEW_NAMES, cfg, np.random.default_rng(0), images=images
    )
