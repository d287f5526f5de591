"""Training, resume, evaluation, prediction and multirun through the real apps (tiny sizes)."""

import csv
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import lightning as L
import numpy as np
import pytest
import torch
from helpers import compose_config, tiny_overrides
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from odmv.deploy.predict import predict
from odmv.io.exr import read_channel, write_exr
from odmv.io.manifest import FringeSpec
from odmv.training.evaluation import evaluate, report
from odmv.training.module import load_module
from odmv.training.run import train


def test_train_writes_checkpoints_metrics_and_tensorboard(trained):
    out, metrics = trained
    assert (out / "checkpoints" / "last.ckpt").is_file()
    assert metrics["best_checkpoint"].startswith(str(out / "checkpoints" / "best-"))
    assert 0 < metrics["test/mae_mm"] < 50 and metrics["test/rmse_mm"] > 0
    assert (out / "metrics.json").is_file() and (out / "split.json").is_file()
    assert metrics["threads"] == torch.get_num_threads()
    # where it came from, so a report rebuilt from the records says the same
    sha1 = hashlib.sha1((Path(metrics["dataset"]) / "manifest.json").read_bytes()).hexdigest()
    assert metrics["dataset_sha1"] == sha1[:12]
    assert metrics["commit"] and metrics["finished"].endswith(" UTC")
    assert f"{os.cpu_count()} CPU cores" in metrics["machine"]
    acc = EventAccumulator(str(out / "tensorboard"), size_guidance={"images": 0}).Reload()
    tags = acc.Tags()
    for tag in (
        "val/fringes",
        "val/depth_gt",
        "val/depth_pred",
        "val/abs_error_0-1mm",
        "val/ocd_masks",
        "val/views_reconstructed",
    ):
        assert tag in tags["images"], tag
    for tag in (
        "train/loss",
        "train/loss_epoch",
        "train/loss_main",
        "train/loss_view",
        "val/mae_mm",
        "lr-Adam",
    ):
        assert tag in tags["scalars"], tag
    ckpt = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)
    assert ckpt["hyper_parameters"]["views"] == ["right", "down", "left", "up"]


@pytest.mark.parametrize("logger", ["csv", "mlflow"])
def test_each_logger_gets_the_curves_and_the_hparams(logger, tiny_dataset, tmp_path):
    """(TensorBoard's, the default's: the test above and tests/test_reliability.py.) The CSV
    log comes with every logger preset."""
    out = tmp_path / "run"
    overrides = tiny_overrides(tiny_dataset, out, f"logger={logger}", f"paths.root_dir={tmp_path}")
    metrics = train(compose_config("train", overrides))
    hparams = (out / "csv" / "hparams.yaml").read_text()
    assert "views: right,down,left,up" in hparams and "loss/alpha" in hparams
    rows = list(csv.DictReader((out / "csv" / "metrics.csv").open()))
    assert any(r.get("val/mae_mm") for r in rows)
    assert not (out / "tensorboard").exists()
    if logger == "mlflow":
        from mlflow.tracking import MlflowClient

        client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
        (run,) = client.search_runs([client.get_experiment_by_name("odmv").experiment_id])
        assert run.data.params["views"] == "right,down,left,up"
        assert run.data.metrics["test/mae_mm"] == pytest.approx(metrics["test/mae_mm"])
        assert "val/mae_mm" in run.data.metrics


@pytest.mark.parametrize("model", ["odmvnet", "mtlnet"])
def test_quarter_turn_augmentation_trains_a_one_view_net(tiny_dataset, tmp_path, model):
    # views=1 with the reference and MTLNet's phase targets: every per-view array is turned
    extra = [f"model={model}", "views=1", "reference=true", "data.augment=rot90"]
    overrides = tiny_overrides(tiny_dataset, tmp_path, *extra)
    if model == "mtlnet":  # a 2D net: no 3D blocks to set
        overrides.remove("model.net.blocks=1")
    metrics = train(compose_config("train", overrides))
    assert np.isfinite(metrics["test/mae_mm"]) and metrics["views"] == ["right"]


def test_resume_continues_from_the_saved_epoch(trained, tiny_dataset, tmp_path):
    out = shutil.copytree(trained[0], tmp_path / "run")  # continued in place: the copy
    (out / "metrics.json").unlink()  # as a run interrupted before its test
    last = out / "checkpoints" / "last.ckpt"
    before = torch.load(last, weights_only=True)
    assert before["epoch"] == 0 and before["global_step"] == 2
    cfg = compose_config(
        "train",
        tiny_overrides(
            tiny_dataset, tmp_path, f"ckpt_path={last}", "trainer.max_epochs=2", "test=false"
        ),
    )
    train(cfg)
    after = torch.load(last, weights_only=True)
    assert after["epoch"] == 1 and after["global_step"] == 4  # one more epoch, not two
    assert after["lr_schedulers"][0]["last_epoch"] == before["lr_schedulers"][0]["last_epoch"] + 1


def test_a_runs_record_names_its_files_so_another_machine_finds_them(
    trained, tmp_path, monkeypatch
):
    """metrics.json names the best checkpoint relative to the run folder (the folder can move)
    and the dataset relative to the checkout; a record with another machine's absolute path
    finds the dataset of that name in this checkout's data/."""
    from odmv.io.runfolder import portable, recorded_dataset
    from odmv.training.checkpoint import best_checkpoint

    run, metrics = trained
    record = json.loads((run / "metrics.json").read_text())
    assert record["best_checkpoint"].startswith("checkpoints/best-")
    moved = shutil.copytree(run, tmp_path / "moved")
    ckpt, _ = best_checkpoint(moved)
    assert ckpt == moved / record["best_checkpoint"] and ckpt.is_file()
    dataset = Path(metrics["dataset"])
    monkeypatch.chdir(dataset.parent)
    assert portable(dataset) == dataset.name and recorded_dataset({"dataset": dataset.name}, moved)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / dataset.name).symlink_to(dataset)
    found = recorded_dataset({"dataset": f"/another/machine/data/{dataset.name}"}, moved)
    # data/ beside the moved run (in a parent of its folder), as a checkout's
    assert found == tmp_path / "data" / dataset.name and (found / "manifest.json").is_file()


def test_the_optimizer_and_schedule_come_from_config(tiny_dataset, tmp_path):
    """optimizer=adamw scheduler=onecycle: AdamW's decoupled decay and OneCycle's state are
    what the checkpoint holds, with no code touched."""
    extra = ("optimizer=adamw", "scheduler=onecycle", "trainer.max_epochs=2", "test=false")
    train(compose_config("train", tiny_overrides(tiny_dataset, tmp_path, *extra)))
    ckpt = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    group = ckpt["optimizer_states"][0]["param_groups"][0]
    assert group["decoupled_weight_decay"] and group["weight_decay"] == 0.01
    sched = ckpt["lr_schedulers"][0]
    assert sched["total_steps"] == 2 and sched["last_epoch"] == 2  # stepped once an epoch


def test_init_from_starts_a_fine_tune_from_a_runs_best_weights(trained, tiny_dataset, tmp_path):
    """init_from=RUN: a new run whose first step starts from the run's best weights, with its
    own settings (view dropout), epochs and optimizer; weights of another net are refused in
    one line naming the checkpoint."""
    from odmv.training.checkpoint import CheckpointError

    run, metrics = trained
    out = tmp_path / "finetune"
    # lr 0: Adam moves nothing, so the weights after its steps are the ones it started from
    extra = (f"init_from={run}", "view_dropout=0.25", "optimizer.lr=0", "test=false")
    train(compose_config("train", tiny_overrides(tiny_dataset, out, *extra)))
    source = torch.load(metrics["best_checkpoint"], weights_only=True)
    tuned = torch.load(out / "checkpoints" / "last.ckpt", weights_only=True)
    assert tuned["global_step"] == 2  # its own two steps, not continued from the run's
    stats = ("running_mean", "running_var", "num_batches_tracked")  # BatchNorm's, not weights
    params = [k for k in source["state_dict"] if k.startswith("net.") and not k.endswith(stats)]
    assert params and all(
        torch.equal(source["state_dict"][k], tuned["state_dict"][k]) for k in params
    )
    wider = tiny_overrides(tiny_dataset, tmp_path / "w", *extra, "model.net.base_width=8")
    with pytest.raises(CheckpointError, match=r"best.*\.ckpt: weights do not fit the net"):
        train(compose_config("train", wider))


def test_a_run_named_by_paths_output_dir_holds_its_config_and_resumes(tiny_dataset, tmp_path):
    """The app, as a user types it: the run folder gets Hydra's .hydra/ (so resume=DIR works),
    no .hydra-only folder is left under ./outputs, and the printed TensorBoard command runs."""
    run = tmp_path / "myrun"
    flags = [o for o in tiny_overrides(tiny_dataset, run) if not o.startswith("paths.")]
    app = [sys.executable, "-m", "odmv.train"]
    first = subprocess.run([*app, f"paths.output_dir={run}", *flags], cwd=tmp_path,
                           capture_output=True, text=True, timeout=600)  # fmt: skip
    assert first.returncode == 0, first.stderr[-2000:]
    assert (run / ".hydra" / "config.yaml").is_file() and not (tmp_path / "outputs").exists()
    (command,) = [line.split()[1] for line in first.stdout.splitlines() if "TensorBoard:" in line]
    assert Path(tmp_path, command).is_file() or Path(command).is_file()
    # a run saved before the training modules moved into odmv/training/ resumes as well
    saved = run / ".hydra" / "config.yaml"
    text = saved.read_text()
    assert "odmv.training.csv_logger.CSVLogger" in text
    saved.write_text(text.replace("odmv.training.csv_logger.", "odmv.csv_logger."))
    again = subprocess.run([*app, f"resume={run}", "trainer.max_epochs=2"], cwd=tmp_path,
                           capture_output=True, text=True, timeout=600)  # fmt: skip
    assert again.returncode == 0, again.stderr[-2000:]
    assert f"run folder: {run}" in again.stdout and not (tmp_path / "outputs").exists()
    rows = list(csv.DictReader((run / "csv" / "metrics.csv").open()))
    assert {r["epoch"] for r in rows if r.get("val/mae_mm")} == {"0", "1"}  # both epochs kept


def test_weight_ema_is_validated_checkpointed_and_tested(tiny_dataset, tmp_path):
    overrides = tiny_overrides(tiny_dataset, tmp_path, "ema=0.5", "trainer.max_epochs=2")
    metrics = train(compose_config("train", overrides))
    best = torch.load(metrics["best_checkpoint"], weights_only=True)
    raw, avg = best["current_model_state"], best["state_dict"]
    assert raw.keys() == avg.keys()
    assert any(not torch.equal(raw[k], avg[k]) for k in avg)  # the average is not the last step
    # the test scored the average (the checkpoint's state_dict), as evaluation loads it
    evaluate_cfg = [f"paths.output_dir={tmp_path / 'eval'}", "accelerator=cpu"]
    em = evaluate(
        compose_config("evaluate", [f"ckpt_path={metrics['best_checkpoint']}", *evaluate_cfg])
    )
    assert em["test/mae_mm"] == pytest.approx(metrics["test/mae_mm"], rel=1e-5)
    swapped = tmp_path / "raw.ckpt"
    torch.save({**best, "state_dict": raw}, swapped)
    er = evaluate(compose_config("evaluate", [f"ckpt_path={swapped}", *evaluate_cfg]))
    assert er["test/mae_mm"] != pytest.approx(metrics["test/mae_mm"], rel=1e-5)
    # last.ckpt is the latest epoch although epoch 1 validated worse (Lightning 2.6's save_last
    # writes it only at a new best); resuming restores both the raw weights and the average
    last = tmp_path / "checkpoints" / "last.ckpt"
    assert best["epoch"] == 0 and torch.load(last, weights_only=True)["global_step"] == 4
    (tmp_path / "metrics.json").unlink()  # as a run interrupted before its test
    cont = tiny_overrides(
        tiny_dataset, tmp_path, "ema=0.5", "trainer.max_epochs=3", f"ckpt_path={last}", "test=false"
    )
    train(compose_config("train", cont))
    after = torch.load(last, weights_only=True)
    assert after["global_step"] == 6 and after["callbacks"]
    assert any(
        not torch.equal(after["state_dict"][k], after["current_model_state"][k]) for k in avg
    )


def test_evaluate_writes_metrics_and_figures(trained, tmp_path):
    out, metrics = trained
    cfg = compose_config(
        "evaluate",
        [
            f"ckpt_path={metrics['best_checkpoint']}",
            f"paths.output_dir={tmp_path}",
            "figures=1",
            "accelerator=cpu",
        ],
    )
    em = evaluate(cfg)
    assert em["test/mae_mm"] == pytest.approx(metrics["test/mae_mm"], rel=1e-5)
    assert em["constant/mae_mm"] > 0 and 140 < em["constant/depth_mm"] < 150
    # per scene family: the test scenes' families, pooling back to the overall figures
    with (tmp_path / "test_scenes.csv").open() as fh:
        families = {r["family"] for r in csv.DictReader(fh)}
    pred = np.load(tmp_path / "test_predictions.npz")
    assert {k.split("/")[1] for k in em if k.startswith("family/")} == families
    n = {f: 0 for f in families}
    with (tmp_path / "test_scenes.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    for r, depth in zip(rows, pred["depth_mm"], strict=True):
        n[r["family"]] += np.isfinite(depth).sum()
    pooled = sum(n[f] * em[f"family/{f}/mae_mm"] for f in families) / sum(n.values())
    assert pooled == pytest.approx(em["test/mae_mm"], rel=1e-4)
    const = sum(n[f] * em[f"family/{f}/constant_mae_mm"] for f in families) / sum(n.values())
    assert const == pytest.approx(em["constant/mae_mm"], rel=1e-4)
    assert "per scene family:" in report(em)
    pngs = list((tmp_path / "figures").glob("*.png"))
    assert len(pngs) == 1 and pngs[0].read_bytes()[:4] == b"\x89PNG"


def _ply_count(path):
    head = path.read_bytes().split(b"end_header\n")[0].decode()
    lines = head.splitlines()
    n = int(next(line for line in lines if line.startswith("element vertex")).split()[-1])
    size = {"float": 4, "uchar": 1}
    per_vertex = sum(size[line.split()[1]] for line in lines if line.startswith("property"))
    assert path.stat().st_size == len(head) + len("end_header\n") + per_vertex * n
    return n


def test_predict_scene_and_image_folder(trained, tiny_dataset, tmp_path, capsys):
    _, metrics = trained
    scene = tiny_dataset / "scenes" / "000004"
    cfg = compose_config(
        "predict",
        [
            f"ckpt_path={metrics['best_checkpoint']}",
            f"input={scene}",
            f"out={tmp_path / 'a'}",
            f"paths.output_dir={tmp_path}",
            "drop_unlit=false",
        ],
    )
    (paths,) = predict(cfg)
    depth = read_channel(paths["depth"], "Z")
    assert depth.shape == (32, 32) and 100 < np.median(depth) < 200  # mm
    assert _ply_count(paths["points"]) == 32 * 32
    # the same views as loose files: same depth
    folder = tmp_path / "images"
    for v in ("right", "down", "left", "up"):
        write_exr(
            folder / f"{v}.exr", {"Y": read_channel(scene / "fringe" / f"{v}_f2_s00.exr", "Y")}
        )
    cfg = compose_config(
        "predict",
        [
            f"ckpt_path={metrics['best_checkpoint']}",
            f"input={folder}",
            f"manifest={tiny_dataset}",
            f"out={tmp_path / 'b'}",
            f"paths.output_dir={tmp_path}",
        ],
    )
    np.testing.assert_array_equal(read_channel(predict(cfg)[0]["depth"], "Z"), depth)
    assert (
        "the 30 px fringe (period in projector px) at phase step 0 of 12" in capsys.readouterr().out
    )


def test_predict_refuses_scenes_of_another_fringe(trained, tmp_path):
    """The checkpoint learned the 30 px fringe; a dataset whose network image is the 240 px
    one (and no full sequences to take the 30 px one from) is refused in one line."""
    from odmv.sim.writer import SimSettings, simulate

    other = tmp_path / "other"
    fringe = FringeSpec(train_frequency=1)
    simulate(SimSettings(out=other, scenes=1, height_px=32, width_px=32, images="training",
                         fringe=fringe), workers=1, progress=False)  # fmt: skip
    cfg = compose_config(
        "predict",
        [f"ckpt_path={trained[1]['best_checkpoint']}", f"input={other}/scenes/000000",
         f"out={tmp_path / 'out'}"],
    )  # fmt: skip
    with pytest.raises(ValueError, match="its dataset holds the 240 px fringe.* the "
                       "checkpoint was trained on the 30 px fringe at step 0 of 12"):  # fmt: skip
        predict(cfg)


def test_multirun_writes_one_csv_with_failed_jobs_and_their_errors(tiny_dataset, tmp_path):
    sweep = tmp_path / "sweep"
    args = [
        a
        for a in tiny_overrides(tiny_dataset, tmp_path)
        if not a.startswith(("paths.output_dir", "data.resolution"))
    ]
    cmd = [
        sys.executable,
        "-m",
        "odmv.train",
        "-m",
        "views=1,2",
        "data.resolution=32,40",
        *args,
        "paths.output_dir=${hydra:runtime.output_dir}",
        f"hydra.sweep.dir={sweep}",
        "trainer.limit_train_batches=1",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    # every job ran; the sweep then exits with 2 and points at the table
    assert done.returncode == 2, done.stderr[-2000:]
    assert done.stderr.strip().endswith(
        f"{sweep / 'results.csv'}: 2 of 4 jobs failed (their rows say why)"
    )
    rows = list(csv.DictReader((sweep / "results.csv").open()))
    assert [(r["views"], r["data.resolution"]) for r in rows] == [
        ("1", "32"),
        ("1", "40"),
        ("2", "32"),
        ("2", "40"),
    ]
    for r in rows:
        if r["data.resolution"] == "32":
            assert r["status"] == "ok" and float(r["test/mae_mm"]) > 0 and not r["error"]
        else:
            assert r["status"] == "failed" and r["error"].startswith("data.resolution: 40x40")


def test_threads_pins_torch_threads_for_the_run(tiny_dataset, tmp_path):
    before = torch.get_num_threads()
    try:
        cfg = compose_config("train", tiny_overrides(tiny_dataset, tmp_path, "threads=1"))
        assert train(cfg)["threads"] == torch.get_num_threads() == 1
        with pytest.raises(ValueError, match="threads"):
            train(compose_config("train", tiny_overrides(tiny_dataset, tmp_path, "threads=0")))
    finally:
        torch.set_num_threads(before)


class GradNorms(L.Callback):
    """The gradients' total norm as the optimizer used them (clipped, not yet zeroed)."""

    seen: list[float] = []

    def on_train_batch_end(self, trainer, module, *args):
        grads = [p.grad for p in module.parameters() if p.grad is not None]
        GradNorms.seen.append(float(torch.nn.utils.get_total_norm(grads)))


def test_bf16_mixed_trains_with_fused_adam_and_clipped_gradients(tiny_dataset, tmp_path):
    """The presets' fused Adam and gradient clipping under bf16-mixed, where Lightning's
    mixed-precision plugin refuses every fused optimizer: the step runs, clipped."""
    GradNorms.seen = []
    overrides = [
        "trainer.precision=bf16-mixed",
        "optimizer.fused=true",
        "trainer.gradient_clip_val=0.001",
        "+callbacks.grad_norms._target_=test_train.GradNorms",
    ]
    metrics = train(compose_config("train", tiny_overrides(tiny_dataset, tmp_path, *overrides)))
    assert np.isfinite(metrics["test/mae_mm"])
    assert len(GradNorms.seen) == 2 and max(GradNorms.seen) <= 0.001 * 1.0001


@pytest.mark.slow
def test_compile_trains_the_same_net_and_saves_plain_weights(tiny_dataset, tmp_path):
    # UNet: the switch is the module's, and a 2D net compiles in a fraction of ODMV-Net's time
    def unet(out, *extra):
        tiny = tiny_overrides(tiny_dataset, out, "model=unet", "views=1", *extra)
        return compose_config("train", [o for o in tiny if not o.startswith("model.net.blocks")])

    eager = train(unet(tmp_path / "e"))
    compiled = train(unet(tmp_path / "c", "compile=default"))
    # the same seed and data: the compiled graph computes the same losses, up to fusion rounding
    assert compiled["test/mae_mm"] == pytest.approx(eager["test/mae_mm"], rel=1e-3)
    ckpt = torch.load(compiled["best_checkpoint"], weights_only=True)
    assert not any("_orig_mod" in k for k in ckpt["state_dict"])  # the plain net's names
    assert ckpt["hyper_parameters"]["compile"] == "default"
    assert load_module(compiled["best_checkpoint"])._compiled is None  # evaluated eagerly


def test_a_run_without_a_progress_bar_prints_a_line_per_epoch(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "run"
    train(compose_config("train", tiny_overrides(tiny_dataset, out, "trainer.max_epochs=2")))
    lines = [x for x in capsys.readouterr().out.splitlines() if x.startswith("epoch ")]
    assert [x.split(":")[0] for x in lines] == ["epoch 1/2", "epoch 2/2"]
    assert "val MAE" in lines[0] and lines[-1].endswith("about 0 min left")


def test_a_busy_machine_is_said_with_what_to_do(monkeypatch):
    import odmv.training.pace

    monkeypatch.setattr(odmv.training.pace.os, "cpu_count", lambda: 2)
    monkeypatch.setattr(odmv.training.pace, "busy_cores", lambda: 1.2)
    note = odmv.training.pace.busy_cores_note(2)
    assert note.startswith("the machine is busy (1.2 of 2 cores in use by other work): 2 torch")
    assert "threads=1" in note and "OMP_WAIT_POLICY=PASSIVE" in note
    monkeypatch.setattr(odmv.training.pace, "busy_cores", lambda: 0.3)
    assert odmv.training.pace.busy_cores_note(2) is None


def test_busy_cores_sees_a_spinning_process_now_not_a_minute_ago():
    """Measured from /proc/stat over a quarter second: a process spinning one core shows as
    about one busy core at once, which the one-minute load average would not."""
    from odmv.training.pace import busy_cores

    spin = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.3)
        assert 0.6 <= busy_cores() <= (os.cpu_count() or 1)
    finally:
        spin.kill()
        spin.wait()


def test_the_paper_preset_on_a_cpu_says_what_comes_next_before_it_starts(tmp_path, capsys):
    from odmv.training.pace import CpuPace

    cfg = compose_config("train", ["model=odmvnet", "views=4", f"data.root={tmp_path / 'ds'}"])
    CpuPace(cfg)
    said = capsys.readouterr().out
    assert said.startswith("on the CPU: odmvnet at 480 px for 200 epochs")
    assert f"Next: rendering its dataset into {tmp_path / 'ds'} (200 scenes at 480x480 px" in said
    assert "then the first training step" in said and not (tmp_path / "ds").exists()
