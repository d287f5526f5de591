"""Small helpers shared by test modules (pytest puts tests/ on sys.path)."""

import sys

import numpy as np
from hydra import compose, initialize_config_dir

from odmv.config import CONF_DIR
from odmv.io.manifest import FringeSpec
from odmv.rig import VIEW_NAMES, Rig
from odmv.sim.render import RenderConfig, render_scene
from odmv.sim.scenes import build_scene

RIG = Rig()
#: how a study trains its rows: the training app in a process of its own, as odmv.reproduce
TRAIN = [sys.executable, "-m", "odmv.train"]
CLEAN = RenderConfig(full_well_e=0.0, read_noise=0.0)  # noise-free
FRINGE = FringeSpec()


def render(parts, size, images="training", cfg=CLEAN):
    """Render ``parts`` on the base plane with the default rig, all four views, size x size."""
    scene = build_scene({"parts": parts})
    return render_scene(
        scene, RIG, size, size, FRINGE, VIEW_NAMES, cfg, np.random.default_rng(0), images=images
    )


def tiny_overrides(dataset, out, *extra):
    """Overrides for a seconds-long training run on ``dataset`` at 32 px, writing into ``out``."""
    return [
        "data=exr",
        f"root={dataset}",
        "data.resolution=32",
        "data.batch_size=2",
        "data.num_workers=0",
        "data.progress=false",
        f"data.cache_dir={out}/cache",
        "model.net.base_width=4",
        "model.net.blocks=1",
        "trainer.max_epochs=1",
        "trainer.accelerator=cpu",
        "trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false",
        "trainer.log_every_n_steps=1",
        "trainer.limit_train_batches=2",
        f"paths.output_dir={out}",
        "log_images=1",
        *extra,
    ]


def compose_config(name, overrides):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(name, overrides=overrides)


def predicted_depth(model, scene, out):
    """odmv.predict of ``model`` (a checkpoint or ONNX file) on one ``scene`` into ``out``:
    the depth map it wrote (mm)."""
    from odmv.deploy.predict import predict
    from odmv.io.exr import read_channel

    cfg = compose_config(
        "predict", [f"ckpt_path={model}", f"input={scene}", f"out={out}", f"paths.output_dir={out}"]
    )
    (written,) = predict(cfg)
    return read_channel(written["depth"], "Z")


def run_app(name, *args, cwd):
    """``python -m odmv.<name> ARGS`` in ``cwd`` as a user runs it (no HYDRA_FULL_ERROR)."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run(
        [sys.executable, "-m", f"odmv.{name}", *args],
        cwd=cwd, capture_output=True, text=True, env=env,
    )  # fmt: skip


def one_line_error(done) -> str:
    """The app's error, asserted to be one line and exit status 2."""
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2, done.stderr[-2000:]
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr[-2000:]
    return lines[0]


def zombie(pid: int) -> bool:
    """Whether process ``pid`` is gone or only awaits its parent's wait (Linux /proc)."""
    from pathlib import Path

    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True
