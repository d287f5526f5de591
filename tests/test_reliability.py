"""Checkpoints, resuming in place, evaluation's data settings, TensorBoard's HPARAMS, quiet
output and big or broken simulations: each through the real apps at tiny sizes."""

import csv
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import compose_config, tiny_overrides
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import plugin_data_pb2

import odmv.sim.writer as writer
from odmv.data.dataset import DataError
from odmv.sim.scenes import SceneError
from odmv.sim.writer import SimSettings, SimulationError, simulate
from odmv.training.checkpoint import CheckpointError
from odmv.training.evaluation import evaluate, report
from odmv.training.module import load_module
from odmv.training.run import train


def _app(app, *args, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", f"odmv.{app}", *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=cwd,
    )


# ---------------------------------------------------------------- checkpoints
def _damaged(kind, ckpt, tmp_path):
    path = tmp_path / f"{kind}.ckpt"
    if kind == "truncated":
        data = ckpt.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif kind == "text":
        path.write_text("not a checkpoint\n")
    elif kind == "foreign":  # a pickled object that weights_only refuses
        torch.save({"state_dict": {}, "optimizer": torch.optim.SGD}, path)
    elif kind == "plain":  # readable, but no net settings
        torch.save({"state_dict": {"w": torch.zeros(2)}}, path)
    return path


@pytest.mark.parametrize(
    ("kind", "message"),
    [
        ("missing", "no such checkpoint"),
        ("truncated", "not a PyTorch checkpoint, or truncated"),
        ("text", "not a PyTorch checkpoint, or truncated"),
        ("foreign", "holds Python objects besides tensors and plain data"),
        ("plain", "not an odmv checkpoint"),
    ],
)
def test_a_bad_checkpoint_is_named_with_its_problem(trained, tmp_path, kind, message):
    _, metrics = trained
    path = _damaged(kind, Path(metrics["best_checkpoint"]), tmp_path)
    with pytest.raises(CheckpointError) as err:
        load_module(path)
    assert str(err.value) == f"{path}: {message}" or str(err.value).startswith(f"{path}: {message}")
    assert "weights_only" not in str(err.value)


def test_evaluate_reports_a_truncated_checkpoint_in_one_line(trained, tmp_path):
    _, metrics = trained
    path = _damaged("truncated", Path(metrics["best_checkpoint"]), tmp_path)
    done = _app("evaluate", f"ckpt_path={path}", f"hydra.run.dir={tmp_path / 'ev'}")
    assert done.returncode == 2
    assert done.stderr.strip() == f"error: {path}: not a PyTorch checkpoint, or truncated"
    assert not (tmp_path / "ev").exists()


def test_continuing_another_net_names_what_differs(trained, tiny_dataset, tmp_path):
    out = shutil.copytree(trained[0], tmp_path / "run")
    (out / "metrics.json").unlink()  # as a run interrupted before its test
    last = out / "checkpoints" / "last.ckpt"
    cfg = compose_config(
        "train",
        tiny_overrides(tiny_dataset, tmp_path, f"ckpt_path={last}", "model.net.base_width=8"),
    )
    with pytest.raises(
        CheckpointError, match=r"last.ckpt: trained with base_width 4 \(this run 8\)"
    ):
        train(cfg)
    cfg = compose_config(
        "train", tiny_overrides(tiny_dataset, tmp_path, f"ckpt_path={last}", "views=2")
    )
    with pytest.raises(CheckpointError, match=r"views right,down,left,up \(this run right,up\)"):
        train(cfg)
    assert not (out / "failed.txt").exists()  # a refused checkpoint is no failure of that run


# ---------------------------------------------------------------- resume in place
def _scalars(folder, tag):
    acc = EventAccumulator(str(folder)).Reload()
    return [(e.step, e.value) for e in acc.Scalars(tag)] if tag in acc.Tags()["scalars"] else []


def test_resume_continues_the_run_folder_logs_and_best_checkpoint(tiny_dataset, tmp_path):
    run, other = tmp_path / "run", tmp_path / "other"
    args = [a for a in tiny_overrides(tiny_dataset, tmp_path) if not a.startswith("paths.")]
    args = [a for a in args if a != "trainer.enable_model_summary=false"]
    first = _app("train", *args, f"hydra.run.dir={run}")
    assert first.returncode == 0, first.stderr[-3000:]
    # a normal run is quiet: no deprecation or logging-interval warnings, real FLOPs
    for noise in ("LeafSpec", "log_every_n_steps", "Total FLOPs: 0", "Traceback"):
        assert noise not in first.stdout + first.stderr, noise
    assert "Total FLOPs" in first.stdout
    assert not (run / "train.log").exists()  # no empty log files

    spent = torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["train_seconds"]
    again = _app("train", f"resume={run}", "trainer.max_epochs=3", f"hydra.run.dir={other}")
    assert again.returncode == 0, again.stderr[-3000:]
    assert f"continuing {run}" in again.stdout and not other.exists()
    with (run / "csv" / "metrics.csv").open() as fh:
        val = {
            int(r["epoch"]): float(r["val/mae_mm"]) for r in csv.DictReader(fh) if r["val/mae_mm"]
        }
    assert sorted(val) == [0, 1, 2]  # the CSV kept the epoch before the resume
    assert [s for s, _ in _scalars(run / "tensorboard", "val/mae_mm")] == sorted(
        s for s, _ in _scalars(run / "tensorboard", "val/mae_mm")
    )
    assert len(_scalars(run / "tensorboard", "val/mae_mm")) == 3  # one curve, three points
    best_epoch = min(val, key=val.get)
    metrics = json.loads((run / "metrics.json").read_text())
    # the record names it relative to the run folder (docs/training.md)
    assert metrics["best_checkpoint"] == f"checkpoints/best-{best_epoch:03d}.ckpt"
    assert (run / metrics["best_checkpoint"]).is_file()
    assert metrics["train_seconds"] > spent > 0  # the time before the resume counts too


# ---------------------------------------------------------------- evaluation
def test_evaluate_keeps_the_checkpoint_data_settings(trained, dataset_copy, tmp_path):
    out, metrics = trained
    saved = torch.load(metrics["best_checkpoint"], weights_only=True)["hyper_parameters"]
    assert os.path.isabs(saved["data_cfg"]["root"]) and os.path.isabs(
        saved["data_cfg"]["cache_dir"]
    )
    overrides = ["data=exr", f"root={dataset_copy}", f"data.cache_dir={tmp_path / 'cache'}"]
    cfg = compose_config(
        "evaluate",
        [
            f"ckpt_path={metrics['best_checkpoint']}",
            f"paths.output_dir={tmp_path / 'ev'}",
            "figures=0",
            "accelerator=cpu",
            "progress=false",
            *overrides,
        ],
    )
    em = evaluate(cfg, overrides)
    # the same 32 px samples from the copy (conf/data/exr.yaml alone would say 480 px)
    assert em["test/mae_mm"] == pytest.approx(metrics["test/mae_mm"], rel=1e-5)
    assert 140 < em["constant/depth_mm"] < 150
    caches = [p.name for p in (tmp_path / "cache").iterdir()]
    assert caches and all("-test-" in name for name in caches)  # the train split not decoded


def test_evaluate_on_a_test_only_dataset_keeps_the_training_constant(
    trained, dataset_copy, tmp_path
):
    """A held-out dataset labelled test only has no training depth of its own: the constant
    predictor is the mean training depth of the checkpoint's dataset, and none where that
    dataset is gone too."""
    _, metrics = trained
    manifest = dataset_copy / "manifest.json"
    m = json.loads(manifest.read_text())
    for scene in m["scenes"]:
        scene["split"] = "test"
    manifest.write_text(json.dumps(m))

    def run(ckpt, name):
        overrides = [f"root={dataset_copy}", f"data.cache_dir={tmp_path / 'cache'}"]
        cfg = compose_config(
            "evaluate",
            [
                f"ckpt_path={ckpt}",
                f"paths.output_dir={tmp_path / name}",
                "figures=0",
                "accelerator=cpu",
                "progress=false",
                *overrides,
            ],
        )
        return evaluate(cfg, overrides)

    own = run(metrics["best_checkpoint"], "own")  # the checkpoint's dataset, its own test split
    base = evaluate(
        compose_config(
            "evaluate",
            [
                f"ckpt_path={metrics['best_checkpoint']}",
                f"paths.output_dir={tmp_path / 'b'}",
                "figures=0",
                "accelerator=cpu",
                "progress=false",
            ],
        ),
        [],
    )
    assert own["constant/depth_mm"] == pytest.approx(base["constant/depth_mm"], rel=1e-9)
    families = [k for k in own if k.startswith("family/") and k.endswith("/mae_mm")]
    families = [k for k in families if "constant" not in k]
    assert families and all(k.replace("/mae_mm", "/constant_mae_mm") in own for k in families)

    ckpt = torch.load(metrics["best_checkpoint"], weights_only=True)
    ckpt["hyper_parameters"]["data_cfg"]["root"] = str(tmp_path / "gone")
    orphan = tmp_path / "orphan.ckpt"
    torch.save(ckpt, orphan)
    alone = run(orphan, "alone")
    assert not any(k.startswith("constant/") or k.endswith("/constant_mae_mm") for k in alone)
    assert alone["test/mae_mm"] > 0
    assert "constant  : none" in report(alone)


def test_evaluate_never_renders_a_missing_dataset(trained, tmp_path):
    _, metrics = trained
    missing = tmp_path / "nowhere"
    cfg = compose_config(
        "evaluate",
        [
            f"ckpt_path={metrics['best_checkpoint']}",
            f"root={missing}",
            "accelerator=cpu",
            f"paths.output_dir={tmp_path / 'ev'}",
        ],
    )
    with pytest.raises(DataError, match="no dataset here"):
        evaluate(cfg, [f"root={missing}"])
    assert not missing.exists()


# ---------------------------------------------------------------- TensorBoard
def test_hparams_tab_lists_settings_and_metrics(trained):
    out, _ = trained
    acc = EventAccumulator(str(out / "tensorboard")).Reload()
    content = acc.PluginTagToContent("hparams")
    exp = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/experiment"])
    names = {h.name for h in exp.experiment.hparam_infos}
    assert {"model", "views", "width", "lr", "resolution", "parameters"} <= names
    metrics = {m.name.tag for m in exp.experiment.metric_infos}
    assert {"val/mae_mm", "test/mae_mm"} <= metrics
    assert {"val/mae_mm", "test/mae_mm"} <= set(acc.Tags()["scalars"])
    yaml = (out / "tensorboard" / "hparams.yaml").read_text()
    assert "views: right,down,left,up" in yaml and "norm/depth_center_mm:" in yaml


# ---------------------------------------------------------------- predict
def test_predict_with_out_makes_no_other_folder(trained, tiny_dataset, tmp_path):
    _, metrics = trained
    done = _app(
        "predict",
        f"ckpt_path={metrics['best_checkpoint']}",
        f"input={tiny_dataset / 'scenes' / '000004'}",
        "out=mine",
        cwd=tmp_path,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]
    assert (tmp_path / "mine" / "depth.exr").is_file()
    assert not (tmp_path / "mine" / "predict.log").exists()


# ---------------------------------------------------------------- simulation
def test_simulate_refuses_a_job_the_disk_cannot_hold(tmp_path, monkeypatch):
    out = tmp_path / "big"
    full = writer.shutil.disk_usage(tmp_path)
    monkeypatch.setattr(writer.shutil, "disk_usage", lambda p: full._replace(free=10**6))
    refusal = r"big: 3 scenes need up to [0-9.]+ MB but only 1.0 MB are free"
    with pytest.raises(SimulationError, match=refusal):
        simulate(SimSettings(out=out, scenes=3, height_px=64, width_px=64), progress=False)
    assert not out.exists()  # refused before anything was written


def test_simulate_announces_a_big_job(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(writer, "BIG_JOB_BYTES", 0)
    out = tmp_path / "ds"
    s = SimSettings(out=out, scenes=2, height_px=32, width_px=32, images="training")
    simulate(s, workers=1, progress=False)
    said = capsys.readouterr().out
    per_scene = writer.scene_bytes_bound(s) / 1e6
    assert f"{out}: 2 scenes, up to" in said and f"({per_scene:.1f} MB each)" in said
    assert "first scene:" in said and "the other 1 take about" in said
    assert s.complete()


def test_a_corrupt_mesh_leaves_nothing_behind(tmp_path):
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    (meshes / "noise.stl").write_bytes(np.random.default_rng(0).bytes(3000))
    out = tmp_path / "ds"
    s = SimSettings(out=out, scenes=2, height_px=32, width_px=32, family="freeform")
    s.mesh_dir = str(meshes)
    with pytest.raises(SceneError, match=r"noise.stl: cannot read mesh"):
        simulate(s, workers=1, progress=False)
    assert not out.exists()


# ---------------------------------------------------------------- a full disk
def _fills_the_disk_after(nbytes):
    """A writer that writes ``nbytes`` of its file, then finds the disk full."""

    def write(tmp: Path) -> None:
        tmp.write_bytes(b"x" * nbytes)
        raise OSError(28, "No space left on device", str(tmp))

    return write


def test_a_full_disk_leaves_the_old_file_and_no_temporary_one(tmp_path):
    from odmv.io.atomic import DiskFullError, write_atomic, write_text

    target = write_text(tmp_path / "metrics.json", '{"old": 1}\n')
    with pytest.raises(DiskFullError) as info:
        write_atomic(target, _fills_the_disk_after(3 * 2**20))
    message = str(info.value)
    assert message.startswith(f"{target}: no space left on {tmp_path}") and "\n" not in message
    assert "wrote 3.0 MiB" in message
    assert target.read_text() == '{"old": 1}\n'  # untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.json"]  # no leftovers


def test_training_on_a_full_disk_stops_with_one_line_and_no_half_checkpoint(
    tiny_dataset, tmp_path, monkeypatch
):
    import odmv.training.checkpoint

    real_save = torch.save
    saved = []

    def save(obj, f, *a, **kw):  # the second checkpoint finds the disk full
        if len(saved) == 1:
            return _fills_the_disk_after(1000)(Path(f))
        saved.append(f)
        return real_save(obj, f, *a, **kw)

    monkeypatch.setattr(odmv.training.checkpoint.torch, "save", save)
    cfg = compose_config("train", tiny_overrides(tiny_dataset, tmp_path / "run"))
    with pytest.raises(ValueError, match="no space left on") as info:
        train(cfg)
    assert "checkpoints" in str(info.value) and "\n" not in str(info.value)
    monkeypatch.setattr(odmv.training.checkpoint.torch, "save", real_save)
    # the one checkpoint written is whole; nothing half-written lies beside it
    files = sorted((tmp_path / "run" / "checkpoints").iterdir())
    assert len(files) == 1 and not files[0].name.startswith(".")
    assert load_module(files[0]) is not None
