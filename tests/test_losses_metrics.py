import math

import pytest
import torch

from odmv.training.losses import LossWeights, composite_loss, depth_loss
from odmv.training.metrics import DepthErrors


def test_depth_loss_is_zero_for_a_perfect_prediction_and_mixes_ssim_and_l1():
    torch.manual_seed(0)
    t = torch.rand(2, 1, 32, 32)
    w = LossWeights()
    perfect = depth_loss(t, t, w)
    assert perfect["loss"].abs() < 1e-6
    shifted = depth_loss(t + 0.1, t, w)  # a constant offset: structure kept, L1 = 0.1
    assert float(shifted["l1"]) == pytest.approx(0.1, abs=1e-6)
    assert 0 < float(shifted["ssim"]) < 0.5
    assert float(shifted["loss"]) == pytest.approx(0.8 * float(shifted["ssim"]) + 0.02, abs=1e-6)


def test_composite_loss_weights_and_skips_missing_outputs():
    torch.manual_seed(0)
    batch = {
        "depth": torch.rand(1, 1, 32, 32),
        "fringes": torch.rand(1, 2, 32, 32) * 2 - 1,
        "lit": torch.randint(0, 2, (1, 2, 32, 32)).float(),
    }
    out = {
        "depth": torch.rand(1, 1, 32, 32),
        "aux": [torch.rand(1, 1, 16, 16), torch.rand(1, 1, 8, 8)],
        "views": torch.zeros(1, 2, 32, 32),
    }
    w = LossWeights()
    t = composite_loss(out, batch, w)
    expected = t["main"] + 0.5 * t["aux1"] + 0.3 * t["aux2"] + 0.2 * t["view"]
    assert float(t["loss"]) == pytest.approx(float(expected), rel=1e-6)
    assert float(t["view"]) == pytest.approx(float((batch["fringes"] ** 2).mean()), rel=1e-6)
    assert set(composite_loss({"depth": out["depth"]}, batch, w)) == {
        "main",
        "main_ssim",
        "main_l1",
        "loss",
    }


def test_occlusion_supervision_prefers_masks_that_match_the_lit_masks():
    lit = torch.zeros(1, 2, 16, 16)
    lit[:, :, :, :8] = 1
    batch = {"depth": torch.zeros(1, 1, 16, 16), "fringes": torch.zeros(1, 2, 16, 16), "lit": lit}
    good = [lit[:, None].clamp(0.05, 0.95), lit[:, None, :, ::2, ::2].clamp(0.05, 0.95)]
    bad = [1 - m for m in good]
    w = LossWeights(occlusion=1.0)
    t_good = composite_loss({"depth": batch["depth"], "occlusion": good}, batch, w)
    t_bad = composite_loss({"depth": batch["depth"], "occlusion": bad}, batch, w)
    assert float(t_good["occlusion"]) == pytest.approx(-math.log(0.95), rel=1e-4)
    assert t_bad["occlusion"] > 10 * t_good["occlusion"]
    assert "occlusion" not in composite_loss(
        {"depth": batch["depth"], "occlusion": good}, batch, LossWeights()
    )  # weight 0: the paper


def test_depth_errors_pixel_means_and_per_image_rmse():
    m = DepthErrors()
    target = torch.full((2, 1, 2, 2), 150.0)
    pred = target.clone()
    pred[0] += 1.0  # image 0: every pixel 1 mm off
    pred[1, 0, 0, 0] += 2.0  # image 1: one pixel 2 mm off
    mask = torch.ones_like(target)
    mask[1, 0, 1, 1] = 0  # excluded pixel
    m.update(pred, target, mask)
    r = m.compute()
    assert float(r["mae_mm"]) == pytest.approx((4 * 1 + 2) / 7)
    assert float(r["mse_mm2"]) == pytest.approx((4 * 1 + 4) / 7)
    assert float(r["rmse_mm"]) == pytest.approx((1.0 + math.sqrt(4 / 3)) / 2)
