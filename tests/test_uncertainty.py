"""Error bars: the split conformal factor, coverage on data with known noise, Mondrian groups,
the sparsification curve and AUSE against hand-made rankings; and a tiny trained run
calibrated, predicting its error bars into the depth's files and the point cloud."""

import json
import math
import shutil

import numpy as np
import pytest

from odmv.training.uncertainty import (
    COVERAGES,
    ause_mm,
    conformal_scale,
    covered,
    sparsification,
)


def test_the_conformal_factor_is_the_finite_sample_quantile_of_the_normalized_errors():
    err = np.arange(1.0, 10.0)  # normalized errors 1 .. 9 with unit scores
    ones = np.ones_like(err)
    assert conformal_scale(err, ones, 0.9) == {None: 9.0}  # ceil(10 x 0.9) = 9th smallest
    assert conformal_scale(err, ones, 0.5) == {None: 5.0}  # ceil(10 x 0.5) = 5th
    assert conformal_scale(err, ones, 0.95) == {None: math.inf}  # 9 pixels cannot promise it
    assert conformal_scale(err, 2 * ones, 0.5) == {None: 2.5}  # in units of the score
    with pytest.raises(ValueError, match="positive"):
        conformal_scale(err, 0 * ones, 0.9)
    with pytest.raises(ValueError, match="coverage=1.5"):
        conformal_scale(err, ones, 1.5)


def test_intervals_hold_the_asked_coverage_on_new_pixels_with_known_noise():
    """Heteroscedastic Gaussian errors, the true sigma as score: the factor is the normal
    quantile (1.645 at 90 %) and new pixels are covered at the asked share; a constant score
    covers as often but with wider intervals where the noise is low."""
    rng = np.random.default_rng(0)
    sigma = rng.uniform(0.01, 0.5, 200_000)
    err = np.abs(rng.normal(0, sigma))
    cal, new = slice(0, 100_000), slice(100_000, None)
    for coverage, z in ((0.8, 1.2816), (0.9, 1.6449), (0.95, 1.9600)):
        q = conformal_scale(err[cal], sigma[cal], coverage)[None]
        assert q == pytest.approx(z, rel=0.02)
        assert covered(err[new], q * sigma[new]) == pytest.approx(coverage, abs=0.005)
    flat = conformal_scale(err[cal], np.ones(100_000), 0.9)[None]
    assert covered(err[new], np.full(100_000, flat)) == pytest.approx(0.9, abs=0.005)
    assert np.mean(1.6449 * sigma[new]) < flat  # the right score gives narrower intervals


def test_each_group_gets_its_own_factor_where_one_would_cover_them_unevenly():
    rng = np.random.default_rng(1)
    group = np.repeat([0, 1], 50_000)
    err = np.abs(rng.normal(0, np.where(group == 0, 0.05, 0.5)))
    score = np.ones_like(err)  # a score blind to the groups
    one = conformal_scale(err, score, 0.9)[None]
    assert covered(err[group == 0], one * score[group == 0]) > 0.99  # over-covered
    assert covered(err[group == 1], one * score[group == 1]) < 0.85  # under-covered
    q = conformal_scale(err, score, 0.9, groups=group)
    assert set(q) == {0, 1} and q[1] / q[0] == pytest.approx(10, rel=0.05)
    for g in (0, 1):
        assert covered(err[group == g], q[g] * score[group == g]) == pytest.approx(0.9, abs=0.01)


def test_the_sparsification_curve_drops_the_most_uncertain_pixels_first():
    err = np.array([4.0, 1.0, 3.0, 2.0, np.nan])  # a pixel without truth does not count
    score = np.array([0.1, 0.4, 0.2, 0.3, 1.0])  # ranks the errors backwards
    curve = sparsification(err, score, shares=(0.25, 0.5, 1.0))
    assert curve["mae_mm"] == [4.0, 3.5, 2.5]  # keeps the largest errors first
    assert curve["oracle_mm"] == [1.0, 1.5, 2.5] and curve["random_mm"] == 2.5
    assert ause_mm(curve) == pytest.approx((3.0 + 2.0) / 2 * 0.25 + (2.0 + 0.0) / 2 * 0.5)
    right = sparsification(err, err, shares=(0.25, 0.5, 1.0))
    assert right["mae_mm"] == right["oracle_mm"] and ause_mm(right) == 0.0


def test_a_score_that_ranks_the_errors_beats_a_random_one():
    rng = np.random.default_rng(2)
    sigma = rng.uniform(0.01, 1.0, 20_000)
    err = np.abs(rng.normal(0, sigma))
    good = sparsification(err, sigma)
    noise = sparsification(err, rng.uniform(size=err.size))
    assert good["mae_mm"][-1] == pytest.approx(err.mean())  # all kept: the plain MAE
    assert good["mae_mm"][-3] < 0.93 * err.mean() < noise["mae_mm"][-3]  # 90 % kept
    assert 0 < ause_mm(good) < 0.5 * ause_mm(noise)


def test_a_calibrated_run_predicts_its_error_bars_into_the_depth_and_the_cloud(
    trained, tiny_dataset, tmp_path
):
    """odmv.study uncertainty RUN calibrates on the validation split and judges on the test
    split; predict then writes each pixel's half width, the trusted mask, and the cloud's
    uncertainty attribute, keeping only trusted points where asked."""
    from helpers import compose_config

    from odmv.deploy.predict import predict
    from odmv.io.exr import read_channel
    from odmv.study.uncertainty import main

    run = shutil.copytree(trained[0], tmp_path / "run")  # the shared run stays as it was
    main([str(run)])
    bars = json.loads((run / "uncertainty.json").read_text())
    assert bars["score"] == "steepness"  # a depth-head net
    factors = [bars["factor"][str(c)] for c in COVERAGES]
    assert factors == sorted(factors) and factors[0] > 0
    test = bars["test"]
    assert 0 <= test["coverage"]["0.9"] <= 1 and test["ause_mm"] >= 0
    assert test["sparsification"]["mae_mm"][-1] == pytest.approx(test["mae_mm"], rel=1e-5)
    split = json.loads((run / "split.json").read_text())
    scene = tiny_dataset / "scenes" / split["test"][0]

    def predicted(out, *extra):
        cfg = compose_config(
            "predict",
            [
                f"ckpt_path={run / bars['checkpoint']}",
                f"input={scene}",
                f"out={out}",
                "colour=false",
                *extra,
            ],
        )
        return predict(cfg)[0]

    written = predicted(tmp_path / "all", "drop_unlit=false")
    half = read_channel(written["uncertainty"], "Z")
    trusted = read_channel(written["trusted"], "Y") > 0
    depth = read_channel(written["depth"], "Z")
    assert half.shape == depth.shape and (half > 0).all() and 0 < trusted.mean() < 1
    points, names = _ply(written["points"])
    assert names[-1] == "uncertainty" and len(points) == np.isfinite(depth).sum()
    np.testing.assert_array_equal(points[:, -1], half[np.isfinite(depth)])
    wide = read_channel(predicted(tmp_path / "wide", "coverage=0.99")["uncertainty"], "Z")
    assert (wide >= half).all() and (wide > half).any()
    kept, _ = _ply(predicted(tmp_path / "kept", "drop_unlit=false", "trusted_only=true")["points"])
    assert len(kept) == (trusted & np.isfinite(depth)).sum()
    with pytest.raises(ValueError, match="coverage=0.7: calibrated at 0.5, 0.8"):
        predicted(tmp_path / "odd", "coverage=0.7")
    # exported, the graph gives the score and carries the calibration: the same error bars
    import onnxruntime as ort

    from odmv.deploy.onnx import METADATA_KEY, export_onnx

    onnx, diff = export_onnx(run / bars["checkpoint"], tmp_path / "onnx")
    session = ort.InferenceSession(str(onnx), providers=["CPUExecutionProvider"])
    assert [o.name for o in session.get_outputs()] == ["depth_mm", "score_mm"] and diff < 1e-3
    meta = json.loads(session.get_modelmeta().custom_metadata_map[METADATA_KEY])
    assert meta["error_bars"]["factor"] == bars["factor"]
    run_onnx = compose_config(
        "predict", [f"ckpt_path={onnx}", f"input={scene}", f"out={tmp_path / 'o'}", "colour=false"]
    )
    by_graph = read_channel(predict(run_onnx)[0]["uncertainty"], "Z")
    np.testing.assert_allclose(by_graph, half, rtol=0.05)  # a 1e-3 mm depth difference, x q


def _ply(path) -> tuple[np.ndarray, list[str]]:
    """A binary PLY of float properties: its vertices (N x properties) and property names."""
    data = path.read_bytes()
    head, _, body = data.partition(b"end_header\n")
    names = [line.split()[-1] for line in head.decode().splitlines() if line.startswith("property")]
    return np.frombuffer(body, "<f4").reshape(-1, len(names)), names


def test_a_capture_whose_fringes_lost_contrast_lies_outside_its_calibration():
    """Michelson contrast within a period: unchanged by the surface's albedo, lowered by blur;
    beyond three of the calibration scenes' standard deviations a scene is flagged."""
    import torch

    from odmv.training.uncertainty import fringe_contrast, outside_calibration

    x = torch.arange(64.0)
    fringe = 0.5 + 0.4 * torch.cos(2 * torch.pi * x / 8)  # contrast 0.8 on every row
    sharp = fringe.expand(1, 2, 64, 64)
    dark = 0.3 * sharp  # a darker surface, the same fringes
    blurred = 0.5 + 0.4 * 0.5 * torch.cos(2 * torch.pi * x / 8).expand(1, 2, 64, 64)
    c = fringe_contrast(torch.cat([sharp, dark, blurred]), 9).tolist()
    assert c[0] == pytest.approx(0.8, abs=0.01) and c[1] == pytest.approx(c[0], abs=1e-4)
    assert c[2] == pytest.approx(0.4, abs=0.01)
    bars = {"contrast": {"mean": 0.8, "std": 0.02, "window_px": 9}}
    assert outside_calibration(c[0], bars) is None
    assert "fringe contrast 0.400 against the calibration scenes' 0.800" in outside_calibration(
        c[2], bars
    )
    assert outside_calibration(0.4, {"contrast": None}) is None  # too few scenes to tell
