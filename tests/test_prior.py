"""Nets that measure, not remember: the twin whose scenes move (pose=random), the prior probe,
and the interior and edge metrics."""

import json

import numpy as np
import pytest
import torch
from helpers import compose_config, tiny_overrides

from odmv.data.prior import prior_summary
from odmv.data.subsets import edge_band
from odmv.io.exr import read_channel
from odmv.io.manifest import load_manifest
from odmv.sim.pose import PoseError, PoseSettings, footprint_shares
from odmv.sim.writer import SimSettings, simulate
from odmv.study import prior
from odmv.training.metrics import edge_bands, wrong_orders
from odmv.training.run import train

RANDOM = PoseSettings(kind="random", unsupported=0.5)


@pytest.fixture(scope="module")
def moving(tmp_path_factory):
    """Twelve 64 px scenes that move, with their full sequences."""
    out = tmp_path_factory.mktemp("pose") / "moving"
    simulate(SimSettings(out=out, scenes=12, height_px=64, width_px=64, seed=5, pose=RANDOM),
             workers=1, progress=False)  # fmt: skip
    return out


def test_the_pose_is_recorded_reproducible_and_inside_the_footprints(moving, tmp_path):
    m = load_manifest(moving)
    poses = [s["pose"] for s in m.scenes]
    assert {p["support"] for p in poses} == {"plane", "surface", "far"}
    offsets = np.array([p["offset_mm"] for p in poses])
    assert np.abs(offsets).max() <= 8.0 and offsets.std() > 2.0
    assert all(abs(a) <= 10.0 for p in poses for a in p["tilt_deg"])
    assert all(0.8 <= p["board_mm"] <= 3.2 for p in poses if "board_mm" in p)
    nominal = min(footprint_shares(m.rig, None).values())
    for p in poses:  # every projector keeps at least 94 % of its nominal share
        assert min(footprint_shares(m.rig, p).values()) >= 0.94 * nominal
    lo, hi = m.extra["depth_range_mm"]
    for s in m.scenes:
        d = read_channel(m.scene_dir(s["id"]) / "depth.exr", "Z")
        assert lo <= d.min() and d.max() <= hi
    # the same seed renders the same poses and pixels
    again = tmp_path / "again"
    simulate(SimSettings(out=again, scenes=3, height_px=64, width_px=64, seed=5, pose=RANDOM),
             workers=1, progress=False)  # fmt: skip
    assert [s["pose"] for s in load_manifest(again).scenes] == poses[:3]
    for sid in ("000000", "000002"):
        a = read_channel(moving / "scenes" / sid / "depth.exr", "Z")
        b = read_channel(again / "scenes" / sid / "depth.exr", "Z")
        assert np.array_equal(a, b)


def test_a_fixed_twin_keeps_its_key_and_the_prior_summary_tells_them_apart(moving, tmp_path):
    s = SimSettings(out=tmp_path / "fixed", scenes=12, height_px=64, width_px=64, seed=5)
    assert "pose" not in s.content_key()  # its datasets keep their names and records
    simulate(s, workers=1, progress=False)
    fixed, moved = prior_summary(load_manifest(s.out)), prior_summary(load_manifest(moving))
    assert fixed["background_mm"]["std"] < 1.0 < 3.0 < moved["background_mm"]["std"]
    assert max(fixed["constant_mae_mm"].values()) < 0.5
    assert min(moved["constant_mae_mm"].values()) > 1.5


def test_pose_settings_outside_the_footprints_are_refused():
    with pytest.raises(PoseError, match="pose.offset_mm"):
        PoseSettings(kind="random", offset_mm=20.0)
    with pytest.raises(PoseError, match="pose.kind"):
        PoseSettings(kind="tilted")


def test_edge_bands_by_hand():
    d = torch.full((1, 1, 8, 8), 150.0)
    d[..., :, 4:] = 148.0  # a 2 mm step between columns 3 and 4
    d[..., 0, 0] = float("nan")
    band = edge_band(d)[0, 0]
    assert band[:, 2:6].all() and not band[:, :2].any() and not band[:, 6:].any()
    b = edge_bands(d)
    assert b["interior"][0, 0, 0, 0] == 0 and b["edge"][0, 0, 0, 0] == 0  # no depth: neither
    assert b["interior"].sum() == 8 * 4 - 1 and b["edge"].sum() == 8 * 4
    d[..., :, 4:] = 149.5  # a 0.5 mm step is no jump
    assert not edge_band(d).any()


def test_wrong_orders_count_lit_pixels_a_period_off():
    maps = torch.zeros(1, 2, 6, 2, 2)
    maps[:, :, 1] = 30.0  # period (px)
    maps[:, :, 3] = 0.3  # gain (mm / px): one period is 9 mm of depth
    maps[:, :, 5] = 150.0
    truth = torch.full((1, 1, 2, 2), 145.0)
    views = truth.repeat(1, 2, 1, 1)
    views[0, 0, 0, 0] += 9.0  # one order off
    views[0, 1, 0, 0] += 4.0  # within half a period
    lit = torch.ones(1, 2, 2, 2)
    lit[0, 1, 1, 1] = 0
    wrong, counted = wrong_orders(views, truth, maps, lit)
    assert (wrong, counted) == (1, 7)


@pytest.fixture(scope="module")
def tiny_run(moving, tmp_path_factory):
    out = tmp_path_factory.mktemp("prior-run")
    metrics = train(compose_config("train", tiny_overrides(moving, out)))
    return out, metrics


def test_records_carry_interior_and_edge_mae(tiny_run):
    _, m = tiny_run
    share = m["test/share_interior"] + m["test/share_edge"]
    assert share == pytest.approx(1.0, abs=1e-6)
    blended = m["test/share_interior"] * m["test/mae_mm_interior"]
    blended += m["test/share_edge"] * m["test/mae_mm_edge"]
    assert blended == pytest.approx(m["test/mae_mm"], rel=1e-4)


def test_the_probe_moves_the_scenes_and_the_classical_method_stays_flat(tiny_run, moving):
    run, _ = tiny_run
    assert prior.main([str(run), "--moves", "2", "--tilt", "0"]) == 0
    result = json.loads((run / "prior.json").read_text())
    assert [m["name"] for m in result["moves"]] == ["none", "2 mm"]
    cl = result["classical"]["moves"]
    assert 0.8 < cl[1]["ratio_mae_mm_interior"] < 1.25  # phase shifting measures
    assert (run / "prior.md").is_file() and (run / "prior.png").stat().st_size > 1000
    # the moved twin holds the test scenes, every depth 2 mm farther where the surface is flat
    twin = next(p for p in moving.parent.glob("prior-*") if p.is_dir())
    m = load_manifest(twin)
    assert {s["split"] for s in m.scenes} == {"test"} and m.extra["simulation"]["move"]
    for s in m.scenes:
        a = read_channel(moving / "scenes" / s["id"] / "depth.exr", "Z")
        b = read_channel(twin / "scenes" / s["id"] / "depth.exr", "Z")
        flat = ~edge_band(torch.from_numpy(a)[None, None], 2)[0, 0].numpy()
        assert np.median((b - a)[flat]) == pytest.approx(2.0, abs=0.01)


def test_the_probe_refuses_an_unfinished_run(tmp_path):
    with pytest.raises(SystemExit, match="not a finished run"):
        prior.main([str(tmp_path)])


def test_simulate_pose_random_from_the_command_line(tmp_path):
    from odmv.data.twin import render_dataset

    cfg = compose_config(
        "simulate",
        [
            f"out={tmp_path / 'd'}",
            "scenes=2",
            "resolution=32",
            "pose=random",
            "workers=1",
            "progress=false",
        ],  # fmt: skip
    )
    assert render_dataset(cfg) == 0
    m = load_manifest(tmp_path / "d")
    assert all("pose" in s for s in m.scenes) and m.extra["simulation"]["pose"]["kind"] == "random"
