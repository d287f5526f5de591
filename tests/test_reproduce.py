"""Metrics that compare and the reproduction pipeline: float32 mm under bf16 autocast, pixel
subsets from every projector's ground truth, the classical row, the report over real runs, and
a resumed reproduction that trains nothing."""

import csv
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import RIG, TRAIN, render
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from odmv.classical.reconstruct import CAPTURES
from odmv.config import CONF_DIR, compose_train, model_configs, nets
from odmv.config import contenders as contenders_of
from odmv.data.normalize import Normalization
from odmv.data.subsets import footprint_from_depth, subset_masks
from odmv.io.runfolder import HELDOUT
from odmv.rig import VIEW_NAMES
from odmv.study.classical import classical_row
from odmv.study.runner import (
    RECORD,
    ReproduceError,
    _run_key,
    plan,
    run_study,
    sweep_overrides,
    trained_key,
)
from odmv.study.tables import ABLATION, VIEWS, tables
from odmv.training.module import FPPModule


def test_depth_in_mm_under_bf16_autocast_matches_float32():
    """A net whose depth is a known constant: under bf16 autocast the mm value must not round
    (bf16 has 1 mm steps at 140 mm and 0.008 steps in normalized units near 1)."""
    module = FPPModule({"_target_": "odmv.models.UNet", "base_width": 4, "dropout": 0.0})
    module.norm = Normalization(1.0, 140.0, 10.0)
    head = module.net.head
    torch.nn.init.zeros_(head.weight)
    torch.nn.init.constant_(head.bias, 0.987654)  # 149.87654 mm
    x = torch.randn(1, 1, 32, 32)
    with torch.no_grad():
        ref = module.depth_mm(module(x))
        with torch.autocast("cpu", dtype=torch.bfloat16):
            out = module(x)
            low = module.depth_mm(out)
    assert out["depth"].dtype == torch.float32 and low.dtype == torch.float32
    assert float((low - 149.87654).abs().max()) < 1e-4
    assert float((low - ref).abs().max()) < 1e-5


def test_every_baseline_head_stays_float32_under_autocast():
    for cls in ("UNet", "HNet", "UHRNet", "MTLNet"):
        net = getattr(__import__("odmv.models", fromlist=[cls]), cls)(1, 4, 0.0).eval()
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
            assert net(torch.randn(1, 1, 32, 32))["depth"].dtype == torch.float32, cls


def test_group_norm_runs_in_float32_under_bf16_autocast():
    """set_norm's GroupNorm: in float32 the plain layer's values; under bf16 autocast it
    normalizes the bf16 volume in float32 (the layer bf16 training keeps in float32)."""
    from odmv.models.blocks import GroupNorm, set_norm

    torch.manual_seed(0)
    plain = torch.nn.GroupNorm(8, 16)  # set_norm: up to 8 groups
    torch.nn.init.normal_(plain.weight)
    torch.nn.init.normal_(plain.bias)
    net = set_norm(torch.nn.Sequential(torch.nn.BatchNorm3d(16)), "group")
    assert type(net[0]) is GroupNorm
    net[0].load_state_dict(plain.state_dict())
    x = torch.randn(2, 16, 4, 8, 8).contiguous(memory_format=torch.channels_last_3d)
    assert torch.equal(net[0](x), plain(x))
    low = x.bfloat16()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = net[0](low)
    assert y.dtype == torch.float32
    torch.testing.assert_close(y, plain(low.float()), rtol=0, atol=0)


def test_subsets_of_a_box_scene():
    """A 4 mm box on the base plane: its shadows are `shadowed`, the image corners outside every
    projector's footprint are `unlit`, the box top (lit by all four) is neither."""
    size = 64
    box = {"shape": "box", "size": [6, 6, 4], "position": [0, 0, 2], "albedo": 0.8}
    r = render([box], size)
    lit = np.stack([r.lit[v] for v in VIEW_NAMES])
    foot = np.stack([r.footprint[v] for v in VIEW_NAMES])
    assert not (lit & ~foot).any()  # lit implies inside the footprint
    masks = subset_masks(lit, foot)
    shadowed, unlit = masks["shadowed"][0], masks["unlit"][0]
    c = size // 2
    assert not shadowed[c, c] and not unlit[c, c]  # box top
    for corner in ((0, 0), (0, -1), (-1, 0), (-1, -1)):
        assert unlit[corner] and not shadowed[corner]
    # the ground beside the box towards each side: shadowed from the projector opposite
    cam = RIG.camera_at(size)
    for x, y in ((4.5, 0), (-4.5, 0), (0, 4.5), (0, -4.5)):
        u, v = cam.project(np.array([x, y, 0.0])).astype(int)
        assert shadowed[v, u], (x, y)
    # the one view (right, lighting from +x) misses the ground on the box's -x side to occlusion,
    # and a band of the field (|y| beyond its footprint's 23 mm) to its footprint; others light both
    hidden, occluded = masks["first_unlit"][0], masks["first_shadowed"][0]
    for (x, y), want in {
        (-4.5, 0): (True, True),
        (4.5, 0): (False, False),
        (0, 15): (True, False),
    }.items():
        u, v = cam.project(np.array([x, y, 0.0])).astype(int)
        assert (hidden[v, u], occluded[v, u]) == want, (x, y)
    # the footprint computed from depth and the rig (the fallback) agrees with the render's
    fallback = footprint_from_depth(RIG, r.depth_mm, VIEW_NAMES)
    assert (fallback == foot).mean() > 0.995


def test_classical_row_is_accurate_where_it_reconstructs(tiny_dataset, tmp_path):
    m = classical_row(tiny_dataset, tmp_path)
    assert m["test/mae_mm"] < 0.1 and 0.5 < m["test/coverage"] <= 1.0
    assert m["test/coverage_unlit"] < m["test/coverage"]
    rows = list(csv.DictReader((tmp_path / "test_scenes.csv").open()))
    assert rows and {"scene", "family", "mae_mm", "coverage"} <= set(rows[0])
    # each subset's pixels per scene, counted as a trained run counts them (the figures pick
    # their scenes by them, so every row of a report shows the same ones)
    total = {k: sum(float(r[k]) for r in rows) for k in ("pixels", "pixels_shadowed")}
    assert total["pixels_shadowed"] / total["pixels"] == pytest.approx(m["test/share_shadowed"])
    with np.load(tmp_path / "test_predictions.npz") as z:
        assert z["pred_mm"].shape == z["depth_mm"].shape
        assert np.isnan(z["pred_mm"]).any() and np.isfinite(z["pred_mm"]).any()


def _compose(overrides, hydra_cfg=False):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("train", overrides=overrides, return_hydra_config=hydra_cfg)


def test_sweeps_expand_to_the_tables_rows():
    # the sweeps train the rows the report declares (odmv.study.tables), in its order
    ablation = [j[0] for j in sweep_overrides("mini", "ablation", []) if "seed=0" in j]
    assert ablation == [f"ablation={key}" for key, _, _ in ABLATION]
    views = [j[0] for j in sweep_overrides("mini", "views", []) if "seed=0" in j]
    assert views == [f"views={s}" for s in range(1, len(VIEWS) + 1)]
    table2 = [r for r in tables("mini")["table2"] if r.model != "classical"]
    assert [r.label for r in table2] == [
        compose_train(["experiment=mini", f"model={m}"]).model.table2.label
        for m in compose_train(["experiment=mini"]).contenders
    ]
    jobs = sweep_overrides("mini", "models", [])
    assert len(jobs) == 14  # seven rows x the mini protocol's two seeds
    assert ["model=unet_s4", "seed=0"] in jobs
    assert len(sweep_overrides("paper", "models", [])) == 6  # no width-24 row: ODMV-Net is 46
    # ODMV-Net at UHRNet's size: width 24 with its full-resolution stage as wide, however the
    # protocol sets the ODMV-Net width of the other rows (notebook round 28)
    w24 = _compose(["experiment=mini", "model=odmvnet_w24"])
    assert (w24.model.net.base_width, w24.model.net.full_width, len(w24.data.views)) == (24, 24, 4)
    assert (w24.threads, _compose(["experiment=paper"]).threads) == (2, None)
    cfg = _compose(["experiment=mini", "model=unet_s4"])
    assert cfg.model.name == "unet" and cfg.model.net.in_channels == 4 * 3  # with the reference
    assert cfg.model.net.base_width == 32  # baselines keep their published width
    cfg = _compose(["experiment=mini"])
    assert cfg.model.net.base_width == 16 and cfg.data.resolution == 64
    paper = _compose(["experiment=paper"])
    assert (paper.data.resolution, paper.data.batch_size, paper.trainer.max_epochs) == (480, 2, 200)
    assert paper.data.simulate.scenes == 252 and paper.model.net.base_width == 46


def test_mini_trains_every_net_for_the_same_epochs_in_one_cosine_cycle():
    # Table II compares nets at equal epochs (the paper's protocol); 70 epochs for all of them
    # (notebook rounds 25-26), the cosine schedule ending at the last one
    contenders = list(_compose(["experiment=mini"]).contenders)
    assert len(contenders) == 7  # the Table II rows that train, the width-24 row among them
    assert contenders == list(contenders_of("extra")) and "odmvnet_w24" in contenders
    for contender in contenders:
        cfg = _compose(["experiment=mini", f"model={contender}"])
        assert (cfg.trainer.max_epochs, cfg.scheduler.T_0) == (70, 70), contender


#: the settings a preset may give each net by name (conf/model/NAME.yaml holds each one's own)
PER_NET = ("widths", "alphas", "lrs")


def _preset_settings(experiment: str) -> dict[str, set[str]]:
    """The nets a preset names in each per-net setting, with the presets and groups it builds
    on (its defaults list)."""
    named = {key: set() for key in PER_NET}
    raw = OmegaConf.load(Path(CONF_DIR, "experiment", f"{experiment}.yaml"))
    sources = [raw]
    for entry in raw.get("defaults") or []:
        if isinstance(entry, str) and entry != "_self_":
            for key, nets_named in _preset_settings(entry).items():
                named[key] |= nets_named
        elif OmegaConf.is_dict(entry):
            for group, option in entry.items():
                sources.append(OmegaConf.load(Path(CONF_DIR, group.strip("/"), f"{option}.yaml")))
    for source in sources:
        for key in PER_NET:
            named[key] |= set(source.get(key) or {})
    return named


@pytest.mark.parametrize(
    "experiment", sorted(p.stem for p in Path(CONF_DIR, "experiment").glob("*.yaml"))
)
def test_every_net_composes_under_every_preset_with_its_settings(experiment):
    """Every model config composes and resolves under every preset; and a preset that gives a
    setting to every net of the paper gives it to every net of the registry, so a net added
    later cannot train under it with the paper's value where the others have the preset's."""
    for model in model_configs():
        cfg = compose_train([f"experiment={experiment}", f"model={model}"])
        OmegaConf.to_container(cfg.model, resolve=True)
        assert float(cfg.optimizer.lr) > 0 and 0 <= float(cfg.loss.alpha) <= 1, model
    registry = set(nets())
    paper = {n for n, c in model_configs().items() if (c.model.get("table2") or {}).get("paper")}
    for key, named in _preset_settings(experiment).items():
        if paper <= named:
            assert registry <= named, f"experiment={experiment}: {key} lacks {registry - named}"


def test_paper_keeps_the_recipe_and_the_other_presets_take_the_improvements():
    def switches(cfg):
        net = cfg.model.net
        return (cfg.norm, cfg.reference, cfg.data.depth_target, cfg.loss.alpha, net.stem_stride)

    assert switches(_compose(["experiment=paper"])) == ("batch", False, "depth", 0.8, 1)
    improved = ("group", True, "height", 0.0, 2)  # pure L1 for ODMV-Net (notebook round 9)
    for preset in ("paper_plus", "mini", "quickstart"):
        assert switches(_compose([f"experiment={preset}"])) == improved, preset
    plus, paper = _compose(["experiment=paper_plus"]), _compose(["experiment=paper"])
    assert (plus.data.resolution, plus.trainer.max_epochs, plus.model.net.base_width) == (
        paper.data.resolution,
        paper.trainer.max_epochs,
        paper.model.net.base_width,
    )
    # the same data-side switches reach the baselines: a fair comparison
    unet = _compose(["experiment=mini", "model=unet"])
    assert (unet.norm, unet.reference, unet.data.depth_target) == improved[:3]
    # L1 where it helped a baseline (hNet, UHRNet: notebook round 21), the paper's SSIM
    # share where it did not (UNet round 9, MTLNet round 21), in both presets that compare
    alpha = {"unet": 0.8, "hnet": 0.0, "uhrnet": 0.0, "mtlnet": 0.8, "unet_s4": 0.8}
    for preset in ("mini", "paper_plus"):
        for contender, want in alpha.items():
            got = _compose([f"experiment={preset}", f"model={contender}"]).loss.alpha
            assert got == want, (preset, contender)
    assert unet.model.net.in_channels == 3  # one view: fringe, sin, cos


def test_quickstart_trains_in_bf16_where_the_cpu_has_bf16_instructions(monkeypatch):
    # the demo's preset: bf16-mixed kept its accuracy and ran faster on an AVX512-BF16 CPU
    # (docs/performance.md); elsewhere bf16 is emulated and unmeasured, so float32 there; the
    # reproduction presets stay float32
    for avx512_bf16, amx, want in (
        (True, False, "bf16-mixed"),
        (False, True, "bf16-mixed"),
        (False, False, "32"),
    ):
        monkeypatch.setattr(torch.cpu, "_is_avx512_bf16_supported", lambda v=avx512_bf16: v)
        monkeypatch.setattr(torch.cpu, "_is_amx_tile_supported", lambda v=amx: v)
        assert _compose(["experiment=quickstart"]).trainer.precision == want
        assert _compose(["experiment=mini"]).trainer.precision == "32"
        assert _compose(["experiment=paper"]).trainer.precision == "32"


def test_plan_trains_a_configuration_shared_by_tables_once(tmp_path):
    jobs = plan("mini", ["views", "ablation", "models"], [0], [], tmp_path)
    names = [j.folder.name for j in jobs]
    assert len(names) == len(set(names)) == 15  # 4 + 6 + 7 rows, ODMV-Net S=4 shared by all
    assert names.count("odmvnet-s4-multitask-seed0") == 1
    assert "odmvnet-s4-multitask-w24-seed0" in names  # another width: another row and folder
    # two configurations under one folder name would overwrite each other's run: refused
    with pytest.raises(ReproduceError, match="odmvnet-s4-multitask-seed0"):
        plan("mini", ["models"], [0], ["widths.odmvnet=24"], tmp_path)


@pytest.mark.parametrize(
    "setting",
    [
        "widths.odmvnet=20",
        "alphas.odmvnet=0.5",
        "lrs.odmvnet=3e-3",
        "full_width=8",
        "loss.occlusion=0.05",  # and a loss weight only ODMV-Net's outputs read
        "loss.view=0.5",
    ],
)
def test_a_row_is_keyed_by_its_own_net_only(tmp_path, setting):
    """Changing ODMV-Net's width, rate, loss or a loss term only it has makes its rows stale,
    never the baselines' rows."""
    today = {j.folder.name: j.key for j in plan("mini", ["models"], [0], [], tmp_path)}
    changed_net = plan("mini", ["models"], [0], [setting], tmp_path)
    changed = sorted(j.folder.name for j in changed_net if j.key != today[j.folder.name])
    assert "odmvnet-s4-multitask-seed0" in changed  # and the width-24 row where it reaches it
    assert set(changed) <= {"odmvnet-s4-multitask-seed0", "odmvnet-s4-multitask-w24-seed0"}


def test_a_setting_added_as_null_keeps_finished_rows_valid(tmp_path):
    """A row saved before a setting existed is not stale while that setting is null today;
    giving it a value is a change."""
    job = plan("mini", ["views"], [0], [], tmp_path)[0]
    saved = _compose(["experiment=mini", *job.overrides])
    assert saved.model.net.gate_init is None
    OmegaConf.set_struct(saved, False)
    del saved.model.net["gate_init"]  # the config as written before the setting existed
    (job.folder / ".hydra").mkdir(parents=True)
    OmegaConf.save(saved, job.folder / ".hydra" / "config.yaml")
    (job.folder / "metrics.json").write_text("{}")  # a finished row
    assert not job.stale() and job.current()
    changed = plan("mini", ["views"], [0], ["model.net.gate_init=neutral"], tmp_path)[0]
    assert changed.folder == job.folder and changed.stale() and not changed.current()


def test_how_checkpoints_are_kept_is_no_part_of_a_rows_key(tmp_path):
    """Rows saved with the checkpoint callbacks of before stay valid; the weight EMA, which
    changes the tested weights, is part of the key."""
    job = plan("mini", ["views"], [0], [], tmp_path)[0]
    saved = _compose(["experiment=mini", *job.overrides])
    OmegaConf.set_struct(saved, False)
    del saved.callbacks["last"]  # the callbacks as saved before last.ckpt had its own
    saved.callbacks.checkpoint.save_last = True
    assert _run_key(saved) == job.key
    assert plan("mini", ["views"], [0], ["ema=0.99"], tmp_path)[0].key != job.key


def test_the_committed_mini_rows_are_current_under_todays_configs():
    """Every row of the mini reproduction's records is what today's configs would train (so
    a refactor of the configs, e.g. the optimizer as a config group, retrains nothing); a
    change that should retrain rows makes this fail and says which."""
    records = sorted((Path(__file__).parents[1] / "experiments/results/mini/runs").glob("*"))
    stale = []
    for folder in records:
        if (folder / "reproduce.json").is_file():
            overrides = json.loads((folder / "reproduce.json").read_text())["overrides"]
            if trained_key(folder) != _run_key(compose_train(overrides)):
                stale.append(folder.name)
    assert len(records) > 20 and not stale, stale


def test_a_record_without_its_config_is_judged_by_its_recorded_key(tmp_path):
    """A record kept without .hydra/config.yaml: its reproduce.json key decides; without a key
    (records kept before keys were written) nothing can be told, and the row counts as done."""
    job = plan("mini", ["views"], [0], [], tmp_path)[0]
    job.record.mkdir(parents=True)
    (job.record / "metrics.json").write_text("{}")
    assert job.result() == job.record and not job.stale() and not job.current()
    (job.record / RECORD).write_text(json.dumps({"overrides": [], "key": job.key}))
    assert job.current() and not job.stale()
    (job.record / RECORD).write_text(json.dumps({"overrides": [], "key": "0" * 8}))
    assert job.stale() and not job.current()


@pytest.mark.slow
def test_reproduce_writes_the_report_and_resumes_without_training(tiny_dataset, tmp_path, capsys):
    overrides = _row_overrides(tiny_dataset, tmp_path, "widths.odmvnet=4", "model.net.blocks=1")
    runs, out = tmp_path / "runs", tmp_path / "report"
    cfg = _reproduce_cfg(overrides, runs, out)
    run_study(cfg, TRAIN)
    metrics = sorted(runs.glob("*/metrics.json"))
    # S = 1..4, the classical row and its captures on fewer images (the last is the row itself)
    assert len(metrics) == 4 + 1 + len(CAPTURES) - 1
    table = (out / "tables.md").read_text()
    for path in metrics:
        m = json.loads(path.read_text())
        assert f"{m['test/mae_mm']:.4f}" in table
    assert "missing" in table  # Table I rows 1-5 were not run
    views = list(csv.DictReader((out / "views.csv").open()))
    assert [r["seeds"] for r in views] == ["1", "1", "1", "1"]
    assert all(float(r["mae_mm"]) > 0 for r in views)
    assert list(out.glob("fig6_*.png")) and list(out.glob("bars_*.png"))
    # every trained row is also scored on the held-out scenes, and its record keeps that
    for path in metrics:
        if not path.parent.name.startswith("classical"):
            held = json.loads((path.parent / HELDOUT).read_text())
            assert held["test/mae_mm"] > 0 and held["dataset"] != str(tiny_dataset.resolve())
            assert f"{held['test/mae_mm']:.4f}" in table  # the report's held-out column
            assert (out / "runs" / path.parent.name / HELDOUT).read_text() == json.dumps(
                held, indent=1
            ) + "\n"
    stamps = {p: p.stat().st_mtime_ns for p in metrics}
    run_study(cfg, TRAIN)  # everything is on disk: nothing is trained again
    assert {p: p.stat().st_mtime_ns for p in metrics} == stamps

    # a row stopped before its end continues from its checkpoint in its own folder; a finished
    # row whose saved configuration differs from today's is kept and named
    cut, changed = runs / "odmvnet-s1-multitask-seed0", runs / "odmvnet-s2-multitask-seed0"
    (cut / "metrics.json").unlink()
    shutil.rmtree(out / "runs" / cut.name)  # a row that stopped has no record either
    saved = cut / ".hydra" / "config.yaml"
    before = saved.read_text()
    edited = changed / ".hydra" / "config.yaml"
    today = trained_key(changed)
    trained_with = OmegaConf.load(edited)
    trained_with.lrs.odmvnet *= 2  # ODMV-Net's rate, which the row's optimizer.lr reads
    OmegaConf.save(trained_with, edited)
    capsys.readouterr()
    run_study(cfg, TRAIN)
    printed = capsys.readouterr().out
    assert f"continuing from {cut / 'checkpoints' / 'last.ckpt'}" in printed
    assert f"note: {changed.name} was trained with another configuration" in printed
    assert "resume=" in (cut / "train.out").read_text() and saved.read_text() == before
    assert (cut / "metrics.json").is_file()
    assert [p for p in metrics if p.parent != cut and p.stat().st_mtime_ns != stamps[p]] == []

    # retrain trains the changed row again, its record replaced by the new run; then it is
    # today's configuration and a second call trains nothing
    again = OmegaConf.merge(cfg, {"retrain": ["odmvnet-s2-*"]})
    assert trained_key(changed) != today
    capsys.readouterr()
    run_study(again, TRAIN)
    printed = capsys.readouterr().out
    assert "(3 done, 1 to train again)" in printed and f"[1/1] {changed.name}:" in printed
    assert trained_key(changed) == trained_key(out / "runs" / changed.name) == today
    assert json.loads((changed / RECORD).read_text())["key"] == today
    stamps = {p: p.stat().st_mtime_ns for p in metrics}
    run_study(again, TRAIN)
    assert "(4 done, 0 to train again)" in capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for p in metrics} == stamps

    # a fresh checkout has the report and its records, not the run folders: nothing is trained
    # again, the tables keep every figure and the figures come from the kept predictions
    kept = sorted((out / "runs").glob("*/metrics.json"))
    assert [p.parent.name for p in kept] == sorted(p.parent.name for p in metrics)
    shown = set()
    for path in (out / "runs").glob("*/test_predictions.npz"):
        with np.load(path) as z:
            shown.add(frozenset(z["scene_id"]))
    assert len(shown) == 1  # every row keeps the figures' scenes, the classical rows too
    assert 0 < len(next(iter(shown))) <= 3  # and only them
    for fig in out.glob("fig*.png"):
        fig.unlink()
    shutil.rmtree(runs)
    capsys.readouterr()
    run_study(cfg, TRAIN)
    assert "4 runs (4 done)" in capsys.readouterr().out and not runs.exists()
    table = (out / "tables.md").read_text()
    for path in kept:
        assert f"{json.loads(path.read_text())['test/mae_mm']:.4f}" in table
    assert list(out.glob("fig6_*.png")) and "missing" in table


def test_a_study_of_its_own_rows_trains_each_once_and_tables_them(tiny_dataset, tmp_path, capsys):
    overrides = _row_overrides(tiny_dataset, tmp_path)
    runs, out = tmp_path / "runs", tmp_path / "study"
    rows = {
        "plain": ["model=unet", "widths.unet=4"],
        "l1": ["model=unet", "widths.unet=4", "alphas.unet=0"],
        "again": ["widths.unet=4", "model=unet"],  # the configuration of `plain`: one run
    }
    cfg = OmegaConf.merge(
        _reproduce_cfg(overrides, runs, out),
        {"tables": [], "classical": False, "heldout": 0, "rows": rows},
    )
    # the rows the robustness pattern names are scored on shifted twins, and their records
    # keep the scores
    cfg.robustness = {"rows": ["l1-*"], "shifts": ["gamma:2"], "scenes": 2}
    run_study(cfg, TRAIN)
    rob = json.loads((out / "runs" / "l1-seed0" / "robustness.json").read_text())
    assert list(rob) == ["nominal", "gamma:2"] and rob["gamma:2"]["test/mae_mm"] > 0
    assert not (runs / "plain-seed0" / "robustness.json").exists()
    assert sorted(p.name for p in runs.iterdir() if not p.name.startswith(".")) == [
        "l1-seed0",
        "plain-seed0",
    ]
    assert not (out / "tables.md").exists()  # no table of the paper was asked for
    table = {r.split("|")[1].strip(): r.split("|")[2:-1] for r in (out / "study.md").open()}
    for label, folder in (("plain", "plain-seed0"), ("l1", "l1-seed0"), ("again", "plain-seed0")):
        m = json.loads((runs / folder / "metrics.json").read_text())
        assert [c.strip() for c in table[label][:2]] == ["1", f"{m['test/mae_mm']:.3f}"]
    capsys.readouterr()
    run_study(cfg, TRAIN)  # resumable like the tables: nothing is trained again
    assert "(2 done)" in capsys.readouterr().out
    with pytest.raises(ReproduceError, match="rows.bad"):
        plan("mini", [], [0], overrides, runs, rows={"bad": ["model=nonet"]})
    # {seed} in a row: each seed's run starts from the same seed's base run
    tuned = plan(
        "mini", [], [0, 1], overrides, runs, rows={"t": [f"init_from={runs}/l1-seed{{seed}}"]}
    )
    assert [(j.folder.name, j.overrides[-2]) for j in tuned] == [
        ("t-seed0", f"init_from={runs}/l1-seed0"),
        ("t-seed1", f"init_from={runs}/l1-seed1"),
    ]


def _row_overrides(dataset, tmp_path, *extra):
    """Train overrides of every row of a seconds-long reproduction on ``dataset`` at 32 px."""
    return [
        "data=exr",
        f"root={dataset}",
        "data.resolution=32",
        "data.batch_size=2",
        f"data.cache_dir={tmp_path}/cache",
        *extra,
        "trainer.max_epochs=1",
        "trainer.limit_train_batches=2",
        "trainer.enable_model_summary=false",
        "log_images=0",
    ]


def _reproduce_cfg(overrides, runs, out):
    return OmegaConf.create(
        {
            "protocol": "mini",
            "tables": ["views"],
            "seeds": [0],
            "overrides": overrides,
            "classical": True,
            "heldout": 4,
            "retrain": [],
            "rows": {},
            "runs_dir": str(runs),
            "out": str(out),
            "records": str(out / "runs"),
        }
    )


@pytest.mark.slow
def test_a_study_with_the_probe_and_the_classical_rows_keeps_both(tiny_dataset, tmp_path):
    """prior=true probes every finished row (kept in its record, tabled in study.md), and a
    study's classical=true scores the classical captures on its test scenes."""
    overrides = _row_overrides(tiny_dataset, tmp_path)
    runs, out = tmp_path / "runs", tmp_path / "study"
    cfg = OmegaConf.merge(
        _reproduce_cfg(overrides, runs, out),
        {"tables": [], "classical": True, "heldout": 0, "prior": True},
    )
    cfg.rows = {"plain": ["model=unet", "widths.unet=4"]}
    run_study(cfg, TRAIN)
    probe = json.loads((out / "runs" / "plain-seed0" / "prior.json").read_text())
    assert [m["name"] for m in probe["moves"]] == ["none", "1 mm", "3 mm", "5 mm", "tilt 5 deg"]
    assert probe["classical"]["moves"][3]["ratio_mae_mm_interior"] < 1.5
    assert "### The prior probe" in (out / "study.md").read_text()
    assert (out / "runs" / "classical" / "metrics.json").is_file()
    assert (out / "runs" / "classical-3x1" / "metrics.json").is_file()


def test_keeping_a_run_keeps_the_robustness_scores_its_record_gained(tmp_path):
    """`odmv.study robustness` scores a committed record in place; keeping the same run again
    must not drop those scores, while a record of another training result is replaced whole."""
    from odmv.study.runner import keep

    folder, record = tmp_path / "run", tmp_path / "record"
    folder.mkdir()
    (folder / "metrics.json").write_text('{"test/mae_mm": 0.2}\n')
    (folder / "robustness.json").write_text(json.dumps({"nominal": {"test/mae_mm": 0.2}}))
    assert keep(folder, record)
    scores = {"nominal": {"test/mae_mm": 0.2}, "dead_view:up": {"test/mae_mm": 0.3}}
    (record / "robustness.json").write_text(json.dumps(scores))  # the study, on the record
    keep(folder, record)
    for where in (record, folder):
        assert json.loads((where / "robustness.json").read_text()) == scores
    (folder / "metrics.json").write_text('{"test/mae_mm": 0.25}\n')  # trained again
    (folder / "robustness.json").write_text(json.dumps({"nominal": {"test/mae_mm": 0.25}}))
    assert keep(folder, record)
    assert list(json.loads((record / "robustness.json").read_text())) == ["nominal"]


def test_a_run_records_its_commit_as_clean_while_result_records_change(tmp_path):
    """A reproduction writes its rows' records into the checkout as it goes; that is no change
    to the code, so the rows after the first still record a clean commit."""
    import subprocess

    from odmv.training.provenance import RESULTS, commit

    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    record, code = tmp_path / RESULTS / "mini" / "metrics.json", tmp_path / "odmv.py"
    record.parent.mkdir(parents=True)
    record.write_text("{}")
    code.write_text("x = 1\n")
    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    sha = commit(tmp_path)
    assert len(sha) >= 7 and "uncommitted" not in sha
    record.write_text('{"test/mae_mm": 0.1}')
    assert commit(tmp_path) == sha
    code.write_text("x = 2\n")
    assert commit(tmp_path) == f"{sha} (with uncommitted changes)"


#: an absolute path as a machine names it: a folder at the root of a POSIX or Windows disk
_MACHINE_PATH = re.compile(
    r"(?<![\w.~/-])/(?:work|tmp|home|root|usr|opt|var|mnt|srv|Users|private|scratch|data|nfs)/"
    r"|\b[A-Z]:\\"
)


def test_committed_records_name_no_machine_path():
    """What experiments/results holds reads the same on any checkout: its datasets, runs and
    logs are named relative to the checkout (a script's #! line aside)."""
    root = Path(__file__).resolve().parents[1]
    listed = subprocess.run(
        ["git", "ls-files", "experiments/results"], cwd=root, capture_output=True, text=True
    ).stdout.split()
    assert len(listed) > 100
    found = []
    for name in listed:
        path = root / name
        if path.suffix in {".npz", ".png"} or not path.is_file():
            continue
        for n, line in enumerate(path.read_text().splitlines(), 1):
            if not line.startswith("#!") and _MACHINE_PATH.search(line):
                found.append(f"{name}:{n}: {_MACHINE_PATH.search(line).group(0)}")
    assert not found, "\n".join(found[:20])


def test_keeping_a_run_names_the_checkouts_paths_relative_to_it(tmp_path, monkeypatch):
    """A run's log and config name the checkout it ran in; its record names them below it."""
    from odmv.study import runner

    monkeypatch.chdir(tmp_path)
    folder, record = tmp_path / "outputs" / "run", tmp_path / "experiments" / "record"
    (folder / ".hydra").mkdir(parents=True)
    (folder / "metrics.json").write_text('{"test/mae_mm": 0.2, "dataset": "data/twin"}\n')
    cfg = compose_train([])
    cfg.data.root = f"{tmp_path}/data/twin"
    OmegaConf.save(cfg, folder / ".hydra" / "config.yaml")
    (folder / "train.out").write_text(f"{tmp_path}/.venv/lib/torch/x.py:1: UserWarning\n")
    monkeypatch.setattr(runner, "KEPT", (*runner.KEPT, "train.out"))  # as a fine-tune's is
    assert runner.keep(folder, record)
    assert OmegaConf.load(record / ".hydra" / "config.yaml").data.root == "data/twin"
    assert (record / "train.out").read_text() == ".venv/lib/torch/x.py:1: UserWarning\n"
