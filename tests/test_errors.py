"""The apps' own errors: one line naming the file or key, exit status 2, nothing left behind."""

import subprocess
import sys

import numpy as np
import pytest
import torch

from odmv.io.exr import read_channel, write_exr
from odmv.training.module import FPPModule, NonFiniteLossError


def _train(tmp_path, *overrides, env=None):
    run = tmp_path / "run"
    cmd = [
        sys.executable,
        "-m",
        "odmv.train",
        f"hydra.run.dir={run}",
        "data.progress=false",
        f"data.cache_dir={tmp_path}/cache",
        "widths.odmvnet=4",
        "model.net.blocks=1",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=1",
        "trainer.accelerator=cpu",
        "trainer.enable_progress_bar=false",
        *overrides,
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, env=env)
    return done, run


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["data=exr"], "error: data.root: no dataset folder given"),
        (["data=exr", "root=DATA", "data.resolution=40"], "error: data.resolution: 40x40"),
        (["data=exr", "root=DATA", "views=[front]"], "error: "),
    ],
)
def test_train_reports_bad_settings_in_one_line(tiny_dataset, tmp_path, overrides, message):
    overrides = [o.replace("DATA", str(tiny_dataset)) for o in overrides]
    done, run = _train(tmp_path, *overrides)
    assert done.returncode == 2, done.stderr[-3000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(message), done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    assert not run.exists()  # no empty run folder left behind


def test_non_finite_fringes_are_refused_naming_the_file(dataset_copy, tmp_path):
    bad = dataset_copy / "scenes" / "000003" / "fringe" / "right_f2_s00.exr"
    image = read_channel(bad, "Y")
    image[5, 7] = np.nan
    write_exr(bad, {"Y": image})
    done, _ = _train(tmp_path, "data=exr", f"root={dataset_copy}", "data.resolution=32")
    assert done.returncode == 2, done.stderr[-3000:]
    assert done.stderr.strip() == f"error: {bad}: 1 non-finite intensity values"


def test_full_error_shows_the_traceback(tmp_path):
    import os

    done, _ = _train(tmp_path, "data=exr", env={**os.environ, "HYDRA_FULL_ERROR": "1"})
    assert done.returncode != 0 and "Traceback" in done.stderr and "data.root" in done.stderr


def test_a_non_finite_loss_stops_training_with_a_clear_message():
    net_cfg = {"_target_": "odmv.models.UNet", "in_channels": 1, "base_width": 4}
    module = FPPModule(net_cfg)
    batch = {
        # NaN depth means "no ground truth" (masked); a NaN input poisons the output
        "fringes": torch.full((2, 1, 32, 32), float("nan")),
        "depth": torch.zeros(2, 1, 32, 32),
        "scene_id": ["000001", "000002"],
    }
    with pytest.raises(NonFiniteLossError, match=r"train/loss: nan at epoch 0.*000001, 000002"):
        module.training_step(batch, 0)


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        ("manifest", "manifest.json: "),
        ("exr", "depth.exr: "),
    ],
)
def test_a_damaged_dataset_file_is_named_in_one_line(dataset_copy, tmp_path, damage, message):
    if damage == "manifest":
        bad = dataset_copy / "manifest.json"
        bad.write_text("{ not json")
    else:
        bad = dataset_copy / "scenes" / "000002" / "depth.exr"
        bad.write_bytes(bad.read_bytes()[:200])
    done, run = _train(tmp_path, "data=exr", f"root={dataset_copy}", "data.resolution=32")
    assert done.returncode == 2, done.stderr[-3000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {bad}"), done.stderr[-3000:]
    assert not run.exists()
