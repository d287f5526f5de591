"""Missing views (odmv.data.views): a net trained with view dropout takes each view's
availability, and a missing view's images cannot move ODMV-Net's depth."""

import shutil

import numpy as np
import pytest
import torch
from helpers import compose_config, tiny_overrides

from odmv.data.dataset import DataError
from odmv.data.views import ViewDropout, drop, with_availability
from odmv.deploy.inference import load_predictor
from odmv.deploy.predict import predict
from odmv.io.exr import read_channel
from odmv.models import ODMVNet
from odmv.models.blocks import split_availability
from odmv.rig import Rig
from odmv.training.evaluation import evaluate
from odmv.training.losses import LossWeights, composite_loss
from odmv.training.run import train


def _net(ablation, **kw):
    torch.manual_seed(0)
    net = ODMVNet(base_width=4, blocks=1, ablation=ablation, view_channels=3, availability=True,
                  norm="group", stem_stride=2, **kw)  # fmt: skip
    return net.eval()


def _inputs(available):
    torch.manual_seed(1)
    images = torch.rand(2, 4 * 3, 32, 32) * 2 - 1
    return with_availability(images, available), images


@pytest.mark.parametrize("ablation", ["multitask", "baseline"])  # with the fusion, and the mean
def test_a_missing_views_images_do_not_move_the_depth(ablation):
    net = _net(ablation)
    available = torch.tensor([[1.0, 0, 1, 1], [1, 1, 1, 0]])
    x, images = _inputs(available)
    with torch.no_grad():
        depth = net(x)["depth"]
        # other images in the missing views (as a dark or a broken projector would give)
        other = images.clone()
        other[0, 3:6] = torch.rand(3, 32, 32)
        other[1, 9:12] = -1
        assert torch.equal(net(with_availability(other, available))["depth"], depth)
        # while a present view's images do move it, and so does declaring a view missing
        other[0, 0:3] = torch.rand(3, 32, 32)
        assert not torch.allclose(net(with_availability(other, available))["depth"], depth)
        everything = with_availability(images, torch.ones(2, 4))
        assert not torch.allclose(net(everything)["depth"], depth)


def test_the_fusion_gives_a_missing_view_no_weight():
    net = _net("multitask")
    feats = torch.rand(2, 8, 4, 16, 16)
    fusion = net.fusion[0].__class__(8)
    available = torch.tensor([[True, False, True, True], [False, False, True, False]])
    _, weights = fusion.attend(feats, torch.rand(2, 1, 4, 16, 16), available)
    assert torch.all(weights[:, 0][~available] == 0)
    torch.testing.assert_close(weights.sum(2), torch.ones(2, 1, 16, 16))
    assert torch.all(weights[1, 0, 2] == 1)  # one view left: all its weight


def test_availability_travels_with_the_inputs_and_dropout_keeps_a_view():
    available = torch.tensor([1.0, 0, 1, 0])
    x = with_availability(torch.rand(4 * 3, 8, 8), available)
    assert x.shape == (16, 8, 8) and torch.all(x[4:8] == 0) and torch.all(x[3] == 1)
    inputs, read = split_availability(x[None], 4)
    assert read.tolist() == [[True, False, True, False]] and inputs.shape == (1, 12, 8, 8)
    sample = {"inputs": with_availability(torch.rand(12, 8, 8), torch.ones(4)),
              "available": torch.ones(4)}  # fmt: skip
    dropped = drop(sample, torch.tensor([True, True, False, True]))
    assert dropped["available"].tolist() == [1, 1, 0, 1] and torch.all(dropped["inputs"][8:12] == 0)

    class Base(torch.utils.data.Dataset):
        def __len__(self):
            return 400

        def __getitem__(self, i):
            return dict(sample)

    torch.manual_seed(0)
    dropout = ViewDropout(Base(), 0.5)
    kept = torch.stack([dropout[i]["available"] for i in range(len(dropout))])
    assert kept.sum(1).min() >= 1  # never every view gone
    assert 0.4 < 1 - kept.mean() < 0.6  # about the probability asked
    with pytest.raises(ValueError, match="view_dropout"):
        ViewDropout(Base(), 1.0)


def test_the_view_loss_leaves_a_missing_view_out():
    fringes = torch.rand(1, 4, 8, 8)
    out = {"depth": torch.zeros(1, 1, 8, 8), "views": torch.zeros(1, 4, 8, 8)}
    batch = {"depth": torch.zeros(1, 1, 8, 8), "fringes": fringes,
             "available": torch.tensor([[1.0, 1, 0, 1]])}  # fmt: skip
    w = LossWeights(alpha=0.0, aux=[], view=1.0)
    before = composite_loss(out, batch, w)["view"]
    batch["fringes"] = fringes.clone()
    batch["fringes"][0, 2] += 5
    assert composite_loss(out, batch, w)["view"] == before
    expected = (fringes[0, [0, 1, 3]] ** 2).mean()
    torch.testing.assert_close(before, expected)


@pytest.mark.parametrize("model", ["odmvnet", "unet"])
def test_training_with_view_dropout(model, tiny_dataset, tmp_path):
    extra = ["view_dropout=0.5", f"model={model}", "views=4", "reference=true"]
    overrides = tiny_overrides(tiny_dataset, tmp_path, *extra)
    if model == "unet":  # a 2D net has no blocks setting
        overrides.remove("model.net.blocks=1")
    cfg = compose_config("train", overrides)
    if model == "unet":  # three channels per view plus its availability
        assert cfg.model.net.in_channels == 4 * 4
    else:
        assert cfg.model.net.availability is True
    metrics = train(cfg)
    assert metrics["test/mae_mm"] > 0
    ckpt = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    assert ckpt["hyper_parameters"]["input_spec"]["availability"] is True
    # a capture with every view: the predictor adds the flags the net was trained with
    predictor = load_predictor(tmp_path / "checkpoints" / "last.ckpt")
    x = predictor.inputs(torch.rand(4, 32, 32).numpy(), Rig())
    assert x.shape == (1, 4 * 4, 32, 32) and torch.all(x[0, 3::4] == 1)
    assert predictor.run(x)["depth_mm"].shape == (1, 1, 32, 32)
    if model == "odmvnet":  # the test split with a projector missing
        ckpt = metrics["best_checkpoint"]
        run = [f"ckpt_path={ckpt}", "accelerator=cpu", "figures=0", "progress=false"]
        full = evaluate(compose_config("evaluate", [*run, f"paths.output_dir={tmp_path}/e1"]))
        down = evaluate(
            compose_config("evaluate", [*run, f"paths.output_dir={tmp_path}/e2", "missing=[down]"])
        )
        assert full["test/mae_mm"] == pytest.approx(metrics["test/mae_mm"], rel=1e-5)
        assert down["test/mae_mm"] > 0 and down["test/mae_mm"] != full["test/mae_mm"]
        # a capture without its down projector's image, and the same scene with views= naming
        # the three it has: the same depth, the missing view given as missing
        scene = tiny_dataset / "scenes" / "000004"
        capture = tmp_path / "capture"
        capture.mkdir()
        for v in ("right", "left", "up"):
            shutil.copy(scene / "fringe" / f"{v}_f2_s00.exr", capture / f"{v}.exr")
        three = predict(_predict_cfg(ckpt, capture, tmp_path / "p1"))
        named = predict(_predict_cfg(ckpt, scene, tmp_path / "p2", "views=[right,left,up]"))
        assert np.array_equal(
            read_channel(three[0]["depth"], "Z"), read_channel(named[0]["depth"], "Z")
        )
    off = compose_config("train", [o for o in overrides if not o.startswith("view_dropout")])
    assert off.data.view_dropout is None and off.model.net.get("availability") is None


def _predict_cfg(ckpt, folder, out, *extra):
    return compose_config(
        "predict",
        [f"ckpt_path={ckpt}", f"input={folder}", f"out={out}", f"paths.output_dir={out}", *extra],
    )


def test_only_a_net_trained_with_view_dropout_is_told_a_view_is_missing(
    trained, tiny_dataset, tmp_path
):
    run, metrics = trained
    cfg = [f"ckpt_path={metrics['best_checkpoint']}", "accelerator=cpu", "figures=0",
           f"paths.output_dir={tmp_path}"]  # fmt: skip
    with pytest.raises(ValueError, match="not trained with view_dropout") as e:
        evaluate(compose_config("evaluate", [*cfg, "missing=[down]"]), [])
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="some, not all"):
        evaluate(compose_config("evaluate", [*cfg, "missing=[sideways]"]), [])
    capture = tmp_path / "capture"
    capture.mkdir()
    for v in ("right", "left", "up"):
        shutil.copy(tiny_dataset / "scenes" / "000004" / "fringe" / f"{v}_f2_s00.exr",
                    capture / f"{v}.exr")  # fmt: skip
    with pytest.raises(DataError, match="no image for view.*down.*view_dropout") as e:
        predict(_predict_cfg(metrics["best_checkpoint"], capture, tmp_path / "p"))
    assert "\n" not in str(e.value)
