import json
import os

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

import odmv.config  # noqa: F401  (registers the resolvers the configs use)
from odmv.config import CONF_DIR  # (and registers the config resolvers)
from odmv.data import DataError, FPPDataModule
from odmv.io.exr import read_channel, write_exr
from odmv.rig import VIEW_SETS


def _dm(root, tmp_path, **kw):
    kw = {
        "views": VIEW_SETS[4],
        "resolution": 64,
        "cache": False,
        "progress": False,
        "cache_dir": str(tmp_path / "cache"),
        **kw,
    }
    dm = FPPDataModule(str(root), **kw)
    dm.prepare_data()
    dm.setup()
    return dm


def _snapshot(root):
    return {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


@pytest.mark.parametrize("n_views", [1, 2, 3, 4])
def test_sample_shapes_ranges_and_view_order(tiny_dataset, tmp_path, n_views):
    views = VIEW_SETS[n_views]
    dm = _dm(tiny_dataset, tmp_path, views=views)
    s = dm.datasets["train"][0]
    assert s["fringes"].shape == (n_views, 64, 64) and s["fringes"].dtype == torch.float32
    assert -1 <= s["fringes"].min() and s["fringes"].max() <= 1
    assert s["depth_mm"].shape == s["valid"].shape == (1, 64, 64)
    assert s["lit"].shape == (n_views, 64, 64) and set(s["lit"].unique().tolist()) <= {0.0, 1.0}
    assert 130 < s["depth_mm"].min() and s["depth_mm"].max() <= 150.0 + 1e-4
    assert torch.allclose(dm.norm.depth_mm(s["depth"]), s["depth_mm"])
    scene = dm.manifest.scene_dir(s["scene_id"])
    for k, v in enumerate(views):  # channel k is view k in canonical order
        raw = read_channel(scene / "fringe" / f"{v}_f2_s00.exr", "Y")
        assert torch.equal(s["fringes"][k], torch.from_numpy(2 * np.clip(raw, 0, 1) - 1))


def test_downsampling_averages_images_and_never_invents_depth(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, tmp_path, resolution=32)
    s = dm.datasets["train"][0]
    scene = dm.manifest.scene_dir(s["scene_id"])
    raw = read_channel(scene / "fringe" / "right_f2_s00.exr", "Y")
    block_mean = raw.reshape(32, 2, 32, 2).mean((1, 3))
    np.testing.assert_allclose((s["fringes"][0].numpy() + 1) / 2, block_mean, atol=1e-6)
    depth = read_channel(scene / "depth.exr", "Z")
    # each output depth is the input sample nearest the output pixel centre
    assert np.array_equal(s["depth_mm"][0].numpy(), depth[1::2, 1::2])


def test_split_is_disjoint_deterministic_and_saved(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, tmp_path)
    labels = {s["id"]: s["split"] for s in dm.manifest.scenes}
    for name, ids in dm.splits.items():
        assert all(labels[i] == name for i in ids)  # the manifest's labels win
    path = dm.save_split(tmp_path / "run" / "split.json")
    assert json.loads(path.read_text())["test"] == dm.splits["test"]

    from odmv.data.dataset import split_scenes

    for s in dm.manifest.scenes:
        s["split"] = None
    a = split_scenes(dm.manifest, {"train": 0.8, "val": 0.1, "test": 0.1}, seed=0)
    b = split_scenes(dm.manifest, {"train": 0.8, "val": 0.1, "test": 0.1}, seed=0)
    c = split_scenes(dm.manifest, {"train": 0.8, "val": 0.1, "test": 0.1}, seed=1)
    assert a == b and a != c
    assert [len(a[k]) for k in ("train", "val", "test")] == [8, 1, 1]
    everything = a["train"] + a["val"] + a["test"]
    assert sorted(everything) == sorted(labels) and len(set(everything)) == 10


def test_cache_gives_identical_tensors_and_rebuilds_on_change(dataset_copy, tmp_path):
    plain = _dm(dataset_copy, tmp_path, views=VIEW_SETS[3], resolution=32)
    cached = _dm(dataset_copy, tmp_path, views=VIEW_SETS[3], resolution=32, cache=True)
    for split in ("train", "val", "test"):
        for i in range(len(plain.datasets[split])):
            a, b = plain.datasets[split][i], cached.datasets[split][i]
            for k in ("fringes", "depth", "depth_mm", "lit", "valid"):
                assert torch.equal(a[k], b[k]), (split, i, k)
    folders = sorted(p.name for p in (tmp_path / "cache").iterdir())
    assert len(folders) == 3
    # rewriting a file the train split reads changes the fingerprint: a new cache is built
    sid = plain.splits["train"][0]
    old = cached.datasets["train"][0]["depth_mm"]
    target = plain.manifest.scene_dir(sid) / "depth.exr"
    write_exr(target, {"Z": read_channel(target, "Z") - 1.0})
    assert torch.equal(cached.datasets["train"][0]["depth_mm"], old)  # the old cache is frozen
    again = _dm(dataset_copy, tmp_path, views=VIEW_SETS[3], resolution=32, cache=True)
    assert len(list((tmp_path / "cache").iterdir())) == 4
    assert torch.equal(again.datasets["train"][0]["depth_mm"], old - 1.0)


def test_reading_never_modifies_the_dataset(tiny_dataset, tmp_path):
    before = _snapshot(tiny_dataset)
    dm = _dm(tiny_dataset, tmp_path, cache=True)
    for batch in dm.train_dataloader():
        assert batch["fringes"].shape[1:] == (4, 64, 64)
    assert _snapshot(tiny_dataset) == before


def test_full_stacks_and_phase_on_request(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, tmp_path, views=VIEW_SETS[2], with_stacks=True)
    s = dm.datasets["val"][0]
    assert s["fringe_stack"].shape == (2, 36, 64, 64)
    assert torch.equal(s["fringe_stack"][:, 24], s["fringes"])  # f2 s00 = the network image
    lit = s["lit"].bool()
    assert torch.isfinite(s["projector_coord"][lit]).all()
    assert torch.isnan(s["projector_coord"][~lit]).all()


def _damage_message(root, tmp_path):
    with pytest.raises(DataError) as e:
        _dm(root, tmp_path)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


def test_bad_inputs_fail_at_setup_with_one_line(dataset_copy, tmp_path):
    scene = dataset_copy / "scenes" / "000003"
    img = scene / "fringe" / "left_f2_s00.exr"
    saved = img.read_bytes()
    img.unlink()
    assert _damage_message(dataset_copy, tmp_path) == f"{img}: no such file"
    img.write_bytes(saved[:300])
    assert _damage_message(dataset_copy, tmp_path).startswith(f"{img}: ")
    img.write_bytes(saved)
    depth_path = scene / "depth.exr"
    depth = read_channel(depth_path, "Z")
    write_exr(depth_path, {"Z": depth[:32]})
    assert "differs from the manifest's (64, 64)" in _damage_message(dataset_copy, tmp_path)
    nan_depth = depth.copy()
    nan_depth[5, 5] = np.nan
    write_exr(depth_path, {"Z": nan_depth})
    assert _damage_message(dataset_copy, tmp_path) == f"{depth_path}: 1 non-finite depth values"
    write_exr(depth_path, {"Z": depth})
    assert _dm(dataset_copy, tmp_path).datasets["train"]  # repaired: fine again


def test_bad_settings_name_the_key(tiny_dataset, tmp_path):
    with pytest.raises(DataError, match=r"^views: unknown view name"):
        _dm(tiny_dataset, tmp_path, views=["right", "front"])
    with pytest.raises(
        DataError, match=r"^data.resolution: 60x60 must be positive multiples of 16"
    ):
        _dm(tiny_dataset, tmp_path, resolution=60)
    with pytest.raises(DataError, match=r"nothing/manifest.json: no dataset here"):
        _dm(tmp_path / "nothing", tmp_path, simulate=None)
    os.makedirs(tmp_path / "empty")
    with pytest.raises(DataError, match=r"empty/manifest.json: no manifest"):
        FPPDataModule(str(tmp_path / "empty"), simulate=None).setup()


def test_synthetic_default_renders_when_missing(tmp_path):
    root = tmp_path / "synthetic"
    sim = {"scenes": 3, "resolution": 64, "images": "training", "workers": 1, "splits": None}
    dm = _dm(root, tmp_path, simulate=sim, split_fractions={"train": 1, "val": 1, "test": 1})
    assert (root / "manifest.json").is_file()
    assert [len(dm.splits[k]) for k in ("train", "val", "test")] == [1, 1, 1]
    assert dm.datasets["test"][0]["fringes"].shape == (4, 64, 64)


def test_hydra_groups_select_views_and_data(tmp_path):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=["views=3", "data=exr", f"root={tmp_path}"])
        assert list(cfg.data.views) == ["right", "left", "up"]
        assert cfg.data.root == str(tmp_path) and cfg.data.simulate is None
        cfg = compose("train", overrides=["views=2"])
        assert list(cfg.data.views) == ["right", "up"]
        assert cfg.data.simulate.images == "training"
        cfg = compose("train", overrides=["views=[up,left]"])
        assert list(cfg.data.views) == ["left", "up"]
        cfg = compose("train", overrides=["views=5"])
        with pytest.raises(Exception, match="views=5: use 1, 2, 3 or 4"):
            list(cfg.data.views)


def test_phase_targets_match_the_phase_shifting_phase(tiny_dataset, tmp_path):
    from odmv.classical.fringe import wrapped_phase

    # the 8-period sequence: at 64 px the 64-period one is finer than a pixel
    dm = _dm(
        tiny_dataset,
        tmp_path,
        views=VIEW_SETS[2],
        with_phase=True,
        with_stacks=True,
        fringe_frequency=1,
        fringe_step=3,
    )
    s = dm.datasets["train"][0]
    assert s["phase_target"].shape == (4, 64, 64)
    lit = s["lit"][0].bool().numpy()
    stack = (s["fringe_stack"][0, 12:24].numpy() + 1) / 2  # right view, 8 periods
    stack = np.roll(stack, -3, axis=0)  # step 3 first: its phase is the input image's phase
    phase, modulation = wrapped_phase(stack)
    sin, cos = s["phase_target"][0].numpy(), s["phase_target"][1].numpy()
    target = np.arctan2(sin, cos)
    good = lit & (modulation > 0.1)
    err = np.abs(np.angle(np.exp(1j * (phase - target))))[good]
    assert good.mean() > 0.3 and np.median(err) < 0.05
    assert (sin[~lit] == 0).all() and (cos[~lit] == 0).all()


def test_a_preset_never_renders_into_a_named_dataset(tmp_path):
    """experiment=mini fills data.simulate; with data=exr the named folder is only read."""
    import hydra

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose(
            "train", overrides=["experiment=mini", "data=exr", f"root={tmp_path / 'mine'}"]
        )
    dm = hydra.utils.instantiate(cfg.data, _convert_="all")
    with pytest.raises(DataError, match=r"mine/manifest.json: no dataset here"):
        dm.prepare_data()
    assert not (tmp_path / "mine").exists()


def test_metric_subsets_use_every_projector_whatever_the_views(tiny_dataset, tmp_path):
    one = _dm(tiny_dataset, tmp_path, views=VIEW_SETS[1]).datasets["test"][0]
    four = _dm(tiny_dataset, tmp_path, views=VIEW_SETS[4]).datasets["test"][0]
    for key in ("shadowed", "unlit", "first_unlit", "first_shadowed"):
        assert one[key].shape == (1, 64, 64)
        assert torch.equal(one[key], four[key])
        assert one[key].sum() > 0
    lit = four["lit"] > 0.5
    assert torch.equal(four["unlit"][0] > 0.5, ~lit.any(0))
    # first_unlit: where the one view a single-view net sees (right) has no fringe, another has
    assert VIEW_SETS[1] == ("right",) and VIEW_SETS[4][0] == "right"
    hidden = four["first_unlit"][0] > 0.5
    assert not (hidden & lit[0]).any() and not (hidden & ~lit[1:].any(0)).any()
    assert torch.equal(hidden, ~lit[0] & lit[1:].any(0))
    # first_shadowed: the part of it that occlusion hides (inside right's footprint)
    shadowed_first = four["first_shadowed"][0] > 0.5
    assert (hidden & ~shadowed_first).any()  # outside right's footprint: a 23 mm band
    assert (
        not (shadowed_first & ~hidden).any()
        and not (shadowed_first & ~(four["shadowed"][0] > 0.5)).any()
    )
    assert one["family"] in ("primitives", "pcb", "freeform")


def test_subsets_without_footprint_file_fall_back_to_the_rig(dataset_copy, tmp_path):
    with_file = _dm(dataset_copy, tmp_path).datasets["test"][0]
    for f in dataset_copy.glob("scenes/*/footprint.exr"):
        f.unlink()
    without = _dm(dataset_copy, tmp_path).datasets["test"][0]
    assert (with_file["shadowed"] == without["shadowed"]).float().mean() > 0.99
    assert torch.equal(with_file["unlit"], without["unlit"])


def test_train_steps_add_one_sample_per_phase_step(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, tmp_path, train_steps=[0, 5], reference=True)
    plain = _dm(tiny_dataset, tmp_path)
    train, n = dm.datasets["train"], len(plain.datasets["train"])
    assert len(train) == 2 * n and len(dm.datasets["val"]) == len(plain.datasets["val"])
    a, b = train[0], train[n]  # the same scene at steps 0 and 5
    assert a["scene_id"] == b["scene_id"] and torch.equal(a["depth"], b["depth"])
    scene = dm.manifest.scene_dir(b["scene_id"])
    raw = read_channel(scene / "fringe" / "right_f2_s05.exr", "Y")
    assert torch.equal(b["fringes"][0], torch.from_numpy(2 * np.clip(raw, 0, 1) - 1))
    # each step's reference phase is shifted by its step: 2 pi * 5 / 12
    ref_a, ref_b = a["inputs"][1:3], b["inputs"][1:3]
    angle = torch.atan2(ref_b[0], ref_b[1]) - torch.atan2(ref_a[0], ref_a[1])
    inside = ref_a.abs().sum(0) > 0
    shift = torch.remainder(angle[inside], 2 * np.pi)
    torch.testing.assert_close(shift, torch.full_like(shift, 2 * np.pi * 5 / 12), atol=1e-4, rtol=0)


def test_train_steps_need_full_sequences_and_valid_steps(tiny_dataset, tmp_path):
    from odmv.sim.writer import SimSettings, simulate

    out = tmp_path / "training-only"
    simulate(SimSettings(out=out, scenes=3, height_px=32, width_px=32, images="training"), 1, False)
    with pytest.raises(DataError, match="train_steps.*images=full"):
        _dm(out, tmp_path, resolution=32, train_steps="all")
    with pytest.raises(DataError, match="train_steps: 12 out of range"):
        _dm(tiny_dataset, tmp_path, resolution=32, train_steps=[12])
    with pytest.raises(DataError, match="train_steps: 'some'"):
        _dm(tiny_dataset, tmp_path, resolution=32, train_steps="some")


def test_height_target_puts_the_reference_plane_at_zero(tiny_dataset, tmp_path):
    dm = _dm(tiny_dataset, tmp_path, depth_target="height")
    samples = [dm.datasets["train"][i] for i in range(len(dm.datasets["train"]))]
    # a scene where the base plane (at the working distance) shows; pcb boards may cover it
    s = max(samples, key=lambda s: (s["depth_mm"] > 150.0 - 1e-3).float().mean())
    plane = s["depth_mm"] > 150.0 - 1e-3
    assert plane.float().mean() > 0.2 and s["depth"][plane].abs().max() < 1e-4
    torch.testing.assert_close(dm.norm.depth_mm(s["depth"]), s["depth_mm"])
    height_mm = 150.0 - s["depth_mm"]
    torch.testing.assert_close(s["depth"], height_mm / 10.0)  # up, in half ranges


@pytest.mark.parametrize("views", [VIEW_SETS[1], VIEW_SETS[3]])
def test_quarter_turns_turn_each_training_sample_and_take_each_view_from_the_one_mapped_onto_it(
    tiny_dataset, tmp_path, views
):
    from odmv.data.augment import NEXT, source_views

    # a turn hands view v's role to NEXT[v] (pinned by the renderer, test_render.py): after
    # one turn, "right" holds what "down" saw
    assert source_views(VIEW_SETS[4], 1) == [v for w in VIEW_SETS[4] for v in NEXT if NEXT[v] == w]
    assert source_views(VIEW_SETS[4], 1) == ["down", "left", "up", "right"]
    assert source_views(VIEW_SETS[4], 2) == ["left", "up", "right", "down"]
    plain = _dm(tiny_dataset, tmp_path, views=VIEW_SETS[4], reference=True, with_phase=True)
    dm = _dm(tiny_dataset, tmp_path, views=views, reference=True, with_phase=True, augment="rot90")
    torch.manual_seed(0)
    turns = []
    for i in range(24):  # three epochs of the 8 training scenes
        i %= len(plain.datasets["train"])
        s, full = dm.datasets["train"][i], plain.datasets["train"][i]
        matches = []
        for k in range(4):
            idx = [VIEW_SETS[4].index(v) for v in source_views(views, k)]
            turn = lambda x, k=k: torch.rot90(x, k, dims=(-2, -1))  # noqa: E731
            per_view = {  # channels per view: 1 fringe, 1 lit, 3 inputs, 2 phase
                n: full[n].reshape(4, -1, 64, 64)[idx].reshape(-1, 64, 64)
                for n in ("fringes", "lit", "inputs", "phase_target")
            }
            if all(torch.equal(s[n], turn(x)) for n, x in per_view.items()) and all(
                torch.equal(s[n], turn(full[n])) for n in ("depth", "valid", "shadowed", "unlit")
            ):
                matches.append(k)
        assert len(matches) == 1, (i, matches)  # one turn explains every array of the sample
        turns += matches
        assert s["fringes"].shape == (len(views), 64, 64)
        # the subsets that name the first projector do not survive a turn, which hands its role
        # to another
        assert "first_unlit" in full and "first_unlit" not in s and "first_shadowed" not in s
    assert set(turns) == {0, 1, 2, 3}
    # validation and test are not turned
    chosen = [VIEW_SETS[4].index(v) for v in views]
    assert torch.equal(
        dm.datasets["val"][0]["fringes"], plain.datasets["val"][0]["fringes"][chosen]
    )
    with pytest.raises(DataError, match="square"):
        _dm(tiny_dataset, tmp_path, resolution=[64, 48], augment="rot90")
    with pytest.raises(DataError, match="data.augment"):
        _dm(tiny_dataset, tmp_path, augment="mirror")
