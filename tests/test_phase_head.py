"""The phase head (head=phase): the torch triangulation layer against the numpy geometry, the
twin's own phase turned into its depth, and every net trained, evaluated, predicted and
exported with the head."""

import dataclasses
import json

import numpy as np
import onnxruntime as ort
import pytest
import torch
from helpers import RIG, compose_config, predicted_depth, tiny_overrides

from odmv.classical.fringe import triangulate_depth
from odmv.classical.geometry import depth_from_offset, triangulation_maps
from odmv.config import in_channels, nets
from odmv.data.dataset import DataError, check_spec, load_scene
from odmv.data.normalize import Normalization
from odmv.deploy.onnx import METADATA_KEY, export_onnx
from odmv.io.exr import read_channel
from odmv.io.manifest import load_manifest
from odmv.models.phase import HEADS, lowest_order, view_depths
from odmv.rig import VIEW_NAMES
from odmv.training.evaluation import evaluate
from odmv.training.losses import LossWeights, composite_loss
from odmv.training.module import FPPModule, load_module
from odmv.training.run import train


@pytest.mark.parametrize("size", [(64, 64), (48, 80)])
def test_triangulation_layer_matches_the_numpy_geometry(size):
    h, w = size
    maps = torch.from_numpy(triangulation_maps(RIG, VIEW_NAMES, h, w, 240.0, 3, 12))
    cam = RIG.camera_at(w, h)
    for i, proj in enumerate(RIG.projectors().values()):
        for delta in (-420.0, -61.7, 0.0, 35.2, 300.0):  # +-3 periods around the plane
            ref = triangulate_depth(maps[i, 0].double().numpy() + delta, cam, proj)
            got = depth_from_offset(torch.full((1, 1, h, w), delta), maps[i][None, None])
            assert np.abs(got[0, 0].numpy() - ref).max() < 1e-4  # mm, in float32
    # the plane at the working distance; a step offsets the phase, not the coordinate
    assert np.allclose(maps[:, 5], 150.0, atol=1e-3) and np.allclose(maps[:, 2], 0.25)


def test_the_twins_phase_and_order_give_its_depth(tiny_dataset):
    """The rendered phase of the 240 px fringe, with its fringe order from classes or from a
    coarse depth up to 4 mm off, through the layer gives the rendered depth on every lit
    pixel: the head's geometry is the twin's."""
    m = load_manifest(tiny_dataset)
    spec = check_spec(m, VIEW_NAMES, 64, 1, 0, calibration=True)
    maps = torch.from_numpy(triangulation_maps(m.rig, VIEW_NAMES, 64, 64, 240.0, 0, 12))[None]
    k = 5
    for sid in ("000001", "000004"):
        raw = load_scene(m, sid, spec)
        coord = torch.from_numpy(raw["projector_coord"])[None]
        order = torch.round((coord - maps[:, :, 0]) / 240.0).nan_to_num(0) - lowest_order(k)
        logits = torch.nn.functional.one_hot(order.long().clamp(0, k - 1), k).permute(0, 1, 4, 2, 3)
        phase = torch.from_numpy(raw["phase_target"])[None]
        truth = torch.from_numpy(raw["depth_mm"])[None]
        off = 4.0 * (2 * torch.rand(truth.shape, generator=torch.Generator().manual_seed(0)) - 1)
        lit = raw["lit"]
        for out, coarse in (
            ({"phase": phase, "order": 20.0 * logits}, None),
            ({"phase": phase}, truth + off),
        ):
            depth = view_depths(out, maps, coarse)[0].numpy()
            err = np.abs(depth - raw["depth_mm"])[lit]
            assert lit.sum() > 1000 and np.median(err) < 1e-3 and np.quantile(err, 0.99) < 0.05


def test_head_phase_refuses_a_dataset_without_a_rig(tiny_dataset):
    m = dataclasses.replace(load_manifest(tiny_dataset), rig=None)
    with pytest.raises(DataError, match="head=phase: .* has no rig calibration"):
        check_spec(m, VIEW_NAMES, 64, None, None, calibration=True)


def test_the_confidence_can_be_trained_against_each_views_error():
    b, s, h, w = 1, 2, 8, 8
    maps = torch.from_numpy(triangulation_maps(RIG, ["right", "up"], h, w, 240.0, 0, 12))[None]
    batch = {
        "depth": torch.zeros(b, 1, h, w),
        "depth_mm": torch.full((b, 1, h, w), 150.0),
        "lit": torch.ones(b, s, h, w),
        "phase_target": torch.zeros(b, 2 * s, h, w),
        "projector_coord": maps[:, :, 0].clone(),
        "calibration": maps,
    }
    out = {
        "depth": torch.zeros(b, 1, h, w),
        "regressed": torch.zeros(b, 1, h, w),
        "phase": torch.zeros(b, 2 * s, h, w),
        "confidence": torch.zeros(b, s + 1, h, w),
        "view_depth_mm": torch.tensor([150.05, 151.0]).view(1, 2, 1, 1).expand(b, s, h, w),
    }
    lit = composite_loss(out, batch, LossWeights(confidence_target="lit"))
    error = composite_loss(out, batch, LossWeights(confidence_target="error"))
    # logits 0: BCE log 2 against all-ones (lit) and against one right, one wrong view alike
    assert torch.isclose(lit["confidence"], torch.tensor(np.log(2.0), dtype=torch.float32))
    assert torch.isclose(error["confidence"], lit["confidence"])
    out["confidence"] = torch.tensor([5.0, -5.0, 0.0]).view(1, 3, 1, 1).expand(b, 3, h, w)
    assert composite_loss(out, batch, LossWeights(confidence_target="error"))["confidence"] < 0.01
    with pytest.raises(ValueError, match="confidence_target.*lit, error, nearest"):
        LossWeights(confidence_target="both")


def test_the_confidence_can_be_trained_to_pick_the_candidate_nearest_the_truth():
    """confidence_target=nearest: the blend's softmax over the views and the regressed depth
    against the one nearest the truth; a missing view is no candidate, a pixel without truth no
    target."""
    b, s, h, w = 1, 2, 8, 8
    maps = torch.from_numpy(triangulation_maps(RIG, ["right", "up"], h, w, 240.0, 0, 12))[None]
    truth = torch.full((b, 1, h, w), 150.0)
    truth[..., 0, 0] = float("nan")
    batch = {
        "depth": torch.zeros(b, 1, h, w), "depth_mm": truth, "lit": torch.ones(b, s, h, w),
        "phase_target": torch.zeros(b, 2 * s, h, w), "calibration": maps,
        "projector_coord": maps[:, :, 0].clone(),
    }  # fmt: skip
    out = {
        "depth": torch.zeros(b, 1, h, w), "regressed": torch.zeros(b, 1, h, w),
        "regressed_mm": torch.full((b, 1, h, w), 150.5), "phase": torch.zeros(b, 2 * s, h, w),
        "confidence": torch.zeros(b, s + 1, h, w, requires_grad=True),
        "view_depth_mm": torch.tensor([150.05, 151.0]).view(1, 2, 1, 1).expand(b, s, h, w),
    }  # fmt: skip
    nearest = LossWeights(confidence_target="nearest")
    loss = composite_loss(out, batch, nearest)["confidence"]
    assert torch.isclose(loss, torch.tensor(np.log(3.0), dtype=torch.float32))  # even logits
    loss.backward()  # descent raises the nearest view's logit, lowers the others'
    grad = out["confidence"].grad[0, :, 1, 1]
    assert grad[0] < 0 < grad[1] and grad[2] > 0 and out["confidence"].grad[0, :, 0, 0].eq(0).all()
    out["confidence"] = torch.tensor([5.0, -5.0, 0.0]).view(1, 3, 1, 1).expand(b, 3, h, w)
    assert composite_loss(out, batch, nearest)["confidence"] < 0.01
    # the first view missing: the regressed depth (0.5 mm off) is nearer than the second (1 mm)
    batch["available"] = torch.tensor([[False, True]])
    out["confidence"] = torch.tensor([0.0, -5.0, 5.0]).view(1, 3, 1, 1).expand(b, 3, h, w)
    assert composite_loss(out, batch, nearest)["confidence"] < 0.01


@pytest.mark.parametrize("head", HEADS)
@pytest.mark.parametrize("model", nets())
def test_every_net_of_the_registry_takes_every_head(model, head):
    """One entry of HEADS is a head option: every net builds with it, the data module carries
    the rig's maps exactly where it reads them, and the net gives depth from its input."""
    views = 4 if model == "odmvnet" else 1
    ov = [f"model={model}", f"widths.{model}=4", f"views={views}", f"head={head}"]
    cfg = compose_config("train", ov + (["model.net.blocks=1"] if model == "odmvnet" else []))
    norm = Normalization.for_working_distance(
        RIG.camera.working_distance_mm, cfg.data.depth_half_range_mm, 1.0, cfg.data.depth_target
    )
    module = FPPModule.from_config(cfg, norm.to_dict(), list(VIEW_NAMES)[:views]).eval()
    reads = HEADS[head]
    assert module.phase_head == reads and cfg.data.calibration == (True if reads else None)
    x = torch.zeros(1, in_channels(cfg.views, cfg.reference, cfg.view_dropout), 32, 32)
    maps = torch.from_numpy(triangulation_maps(RIG, list(VIEW_NAMES)[:views], 32, 32, 240.0, 0, 12))
    with torch.no_grad():
        out = module(x, maps[None] if reads else None)
    assert out["depth"].shape[-2:] == (32, 32) and ("weights" in out) == reads


@pytest.fixture(scope="module")
def phase_runs(tiny_dataset, tmp_path_factory):
    """Each net trained for one epoch with the phase head (UHRNet's confidence against the
    nearest candidate): {model: (run folder, metrics)}."""
    runs = {}
    for model, views in (("odmvnet", 4), ("unet", 1), ("hnet", 1), ("uhrnet", 1), ("mtlnet", 2)):
        out = tmp_path_factory.mktemp(f"phase-{model}")
        ov = [o for o in tiny_overrides(tiny_dataset, out) if not o.startswith("model.net.b")]
        ov += [f"model={model}", f"widths.{model}=4", f"views={views}", "head=phase"]
        ov += ["reference=true", "data.fringe_frequency=1"]
        ov += ["model.net.blocks=1"] if model == "odmvnet" else []
        # the candidates' own target, in a real training step
        ov += ["loss.confidence_target=nearest"] if model == "uhrnet" else []
        runs[model] = out, train(compose_config("train", ov))
    return runs


@pytest.mark.slow
@pytest.mark.parametrize("model", nets())
def test_every_net_trains_with_the_phase_head(phase_runs, model):
    _, metrics = phase_runs[model]
    assert np.isfinite(metrics["test/mae_mm"]) and metrics["test/mae_mm"] < 20
    assert 0 <= metrics["test/order_wrong"] <= 1  # lit view pixels a fringe order off
    module = load_module(metrics["best_checkpoint"])
    assert module.phase_head and module.hparams.input_spec["head"] == "phase"
    with pytest.raises(ValueError, match="calibration maps"):
        module(torch.zeros(1, len(module.hparams.views) * 3, 32, 32))


@pytest.mark.slow
@pytest.mark.parametrize("model", nets())
def test_a_phase_head_net_evaluates_predicts_and_exports(model, phase_runs, tiny_dataset, tmp_path):
    run, metrics = phase_runs[model]
    ckpt = metrics["best_checkpoint"]
    views = list(load_module(ckpt).hparams.views)
    cfg = compose_config(
        "evaluate",
        [f"ckpt_path={ckpt}", f"paths.output_dir={tmp_path / 'eval'}", "figures=1"]
        + ["accelerator=cpu", "progress=false"],
    )
    assert evaluate(cfg)["test/mae_mm"] == pytest.approx(metrics["test/mae_mm"], rel=1e-5)

    path, diff = export_onnx(ckpt, tmp_path / "export")
    assert diff < 1e-3
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in session.get_inputs()] == ["inputs", "calibration"]
    assert [o.name for o in session.get_outputs()] == ["depth_mm", "weights"]
    meta = json.loads(session.get_modelmeta().custom_metadata_map[METADATA_KEY])
    assert meta["input_spec"]["head"] == "phase"

    scene = tiny_dataset / "scenes" / "000004"
    depths = {}
    for name, model in (("ckpt", ckpt), ("onnx", path)):
        depths[name] = predicted_depth(model, scene, tmp_path / name)
        weights = [read_channel(tmp_path / name / "weights.exr", c) for c in (*views, "regressed")]
        np.testing.assert_allclose(np.sum(weights, 0), 1.0, atol=1e-5)
    assert np.abs(depths["onnx"] - depths["ckpt"]).max() < 1e-3
