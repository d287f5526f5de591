"""The reference-plane phase input: physically the phase the flat plane shows, wired through the
data module, every net, training and prediction."""

import numpy as np
import pytest
import torch
from helpers import RIG, render
from hydra import compose, initialize_config_dir

from odmv.config import CONF_DIR
from odmv.data import FPPDataModule
from odmv.data.reference import network_input, reference_mode, reference_phase
from odmv.deploy.predict import predict
from odmv.io.exr import read_channel
from odmv.rig import VIEW_NAMES
from odmv.training.module import load_module
from odmv.training.run import train


def test_reference_phase_is_the_flat_planes_phase():
    size, period, step = 64, 240.0, 3
    r = render([], size)
    ref = reference_phase(RIG, VIEW_NAMES, size, size, period, step, 12)
    assert ref.shape == (4, 2, size, size)
    for k, v in enumerate(VIEW_NAMES):
        lit = r.lit[v]
        phase = 2 * np.pi * (r.projector_coord[v] / period + step / 12)
        np.testing.assert_allclose(ref[k, 0][lit], np.sin(phase[lit]), atol=1e-3)
        np.testing.assert_allclose(ref[k, 1][lit], np.cos(phase[lit]), atol=1e-3)
        outside = ~r.lit[v] & (ref[k] == 0).all(0)
        assert outside.any()  # no phase outside the projector's footprint


def test_network_input_keeps_each_views_channels_together():
    fringes = torch.arange(2 * 4 * 3, dtype=torch.float32).reshape(2, 3, 2, 2)  # B S H W
    ref = -torch.ones(3, 2, 2, 2)
    x = network_input(fringes, ref)
    assert x.shape == (2, 9, 2, 2)
    torch.testing.assert_close(x[:, 0::3], fringes)
    assert (x[:, 1::3] == -1).all() and (x[:, 2::3] == -1).all()


@pytest.mark.parametrize("mode", [True, "demod"])
def test_samples_carry_the_input_with_reference(tiny_dataset, tmp_path, mode):
    dm = FPPDataModule(
        str(tiny_dataset), resolution=32, reference=mode, cache=False, progress=False
    )
    dm.prepare_data()
    dm.setup()
    s = dm.datasets["test"][0]
    assert s["inputs"].shape == (12, 32, 32)
    torch.testing.assert_close(s["inputs"][0::3], s["fringes"])
    ref = dm.datasets["test"].reference  # S x 2 x H x W: sin, cos
    carrier = s["fringes"] if mode == "demod" else 1.0
    torch.testing.assert_close(s["inputs"][1::3], carrier * ref[:, 0])
    torch.testing.assert_close(s["inputs"][2::3], carrier * ref[:, 1])


def test_demodulation_leaves_the_phase_difference_after_a_local_average():
    # a flat surface lifted by dphi: I = a + b cos(phi_ref + dphi); one period's average of
    # I * (sin, cos)(phi_ref) is (b/2) (-sin dphi, cos dphi)
    period, a, b, dphi = 16, 0.1, 0.7, 0.9
    phi_ref = 2 * np.pi * np.arange(period) / period
    image = torch.tensor(a + b * np.cos(phi_ref + dphi), dtype=torch.float32)[None, None, :]
    ref = torch.tensor(np.stack([np.sin(phi_ref), np.cos(phi_ref)]), dtype=torch.float32)
    x = network_input(image, ref[None, :, None, :], "demod")  # 1 view, 1 x period
    sin_avg, cos_avg = x[1].mean(), x[2].mean()
    assert float(sin_avg) == pytest.approx(-b / 2 * np.sin(dphi), abs=1e-6)
    assert float(cos_avg) == pytest.approx(b / 2 * np.cos(dphi), abs=1e-6)
    with pytest.raises(ValueError, match="reference: 'mixed' unknown"):
        reference_mode("mixed")


@pytest.mark.parametrize(
    ("model", "mode"),
    [("odmvnet", "true"), ("unet", "true"), ("mtlnet", "true"), ("unet", "demod")],
)
def test_training_and_prediction_with_the_reference(tiny_dataset, tmp_path, model, mode):
    overrides = [
        f"model={model}",
        "views=2",
        f"reference={mode}",
        "data=exr",
        f"root={tiny_dataset}",
        "data.resolution=32",
        "data.batch_size=2",
        "data.progress=false",
        f"data.cache_dir={tmp_path}/cache",
        f"widths.{model}=4",
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=2",
        "trainer.accelerator=cpu",
        "trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false",
        f"paths.output_dir={tmp_path}",
        "log_images=0",
    ]
    if model == "odmvnet":
        overrides.append("model.net.blocks=1")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        metrics = train(compose("train", overrides=overrides))
        assert metrics["test/mae_mm"] > 0
        cfg = compose(
            "predict",
            [
                f"ckpt_path={metrics['best_checkpoint']}",
                f"input={tiny_dataset / 'scenes' / '000004'}",
                f"out={tmp_path / 'pred'}",
                f"paths.output_dir={tmp_path}",
            ],
        )
        depth = read_channel(predict(cfg)[0]["depth"], "Z")
    assert depth.shape == (32, 32) and np.isfinite(depth).all()
    # predict rebuilds the net's input from the images and the rig: the test's own depth
    module = load_module(metrics["best_checkpoint"]).eval()
    data_cfg = {k: v for k, v in module.hparams.data_cfg.items() if k != "_target_"}
    dm = FPPDataModule(**{**data_cfg, "cache": False, "progress": False})
    dm.setup()
    ds = next(d for d in dm.datasets.values() if "000004" in d.ids)
    sample = ds[ds.ids.index("000004")]
    with torch.no_grad():
        expected = module.depth_mm(module(sample["inputs"][None]))[0, 0].numpy()
    np.testing.assert_allclose(depth, expected, atol=1e-3)
