"""Every fault one line, nothing lost: full and read-only disks (real tmpfs mounts where the
machine allows them), outputs that would overwrite inputs, run folders that belong to another
run, captures without a fringe, a killed training resumed bit for bit, and Hydra's own errors."""

import os
import shutil
import signal
import subprocess
import sys
import time
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import compose_config, one_line_error, run_app, tiny_overrides, zombie

from odmv.io.exr import read_channel, write_exr

PY = sys.executable
_VIEWS = ("right", "down", "left", "up")


@contextmanager
def _mounted(path: Path, options: str):
    path.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)], capture_output=True
    )
    if done.returncode:
        pytest.skip("cannot mount a tmpfs here (needs root and mount): no real full disk")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


@pytest.fixture
def small_disk(tmp_path):
    """A real 1 MiB file system."""
    with _mounted(tmp_path / "disk", "size=1m") as disk:
        yield disk


@pytest.fixture
def read_only_disk(tmp_path):
    with _mounted(tmp_path / "ro", "ro,size=64m") as disk:
        yield disk


# ---------------------------------------------------------------- Hydra's and the apps' keys
@pytest.mark.parametrize(
    "args, expected",
    [
        (["model=nosuch"], "error: model=nosuch: no such model; choose one of hnet, mtlnet,"),
        (["trainer.max_epochz=3"], "did you mean trainer.max_epochs?"),
        (["+out=x"], "error: out: not a setting of this app"),
        (["trainer.max_epochs=0"], "error: trainer.max_epochs=0: at least 1"),
        (["model.net.base_width=0"], "error: model.net.base_width: 0; a positive channel count"),
    ],
)
def test_a_wrong_key_is_one_line_naming_it(args, expected, tiny_dataset, tmp_path):
    extra = [a for a in tiny_overrides(tiny_dataset, tmp_path / "run") if "base_width" not in a]
    line = one_line_error(run_app("train", *extra, *args, cwd=tmp_path))
    assert expected in line
    assert not (tmp_path / "run").exists()  # nothing left behind


def test_simulate_refuses_no_scenes(tmp_path):
    line = one_line_error(run_app("simulate", "scenes=0", "out=ds", cwd=tmp_path))
    assert line == "error: scenes=0: render at least one scene"
    assert not (tmp_path / "ds").exists()


# ---------------------------------------------------------------- full and read-only disks
def test_a_checkpoint_on_a_real_full_disk_is_one_line_and_keeps_the_old_one(small_disk):
    from odmv.io.atomic import DiskFullError
    from odmv.training.checkpoint import AtomicCheckpointIO

    target = small_disk / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint({"w": torch.zeros(16)}, target)
    old = target.read_bytes()
    with pytest.raises(DiskFullError) as info:  # torch.save: its own RuntimeError on ENOSPC
        AtomicCheckpointIO().save_checkpoint({"w": torch.zeros(1 << 20)}, target)
    assert str(info.value).startswith(f"{target}: no space left on {small_disk}")
    assert "\n" not in str(info.value)
    assert target.read_bytes() == old
    assert sorted(p.name for p in small_disk.iterdir()) == ["last.ckpt"]


def test_an_exr_on_a_real_full_disk_is_one_line(small_disk):
    from odmv.io.atomic import DiskFullError

    with pytest.raises(DiskFullError, match="no space left"):
        write_exr(
            small_disk / "big.exr", {"Y": np.random.default_rng(0).random((800, 800), np.float32)}
        )
    assert list(small_disk.iterdir()) == []


def test_a_writers_runtime_error_is_a_full_disk_only_when_the_disk_is_full(tmp_path, monkeypatch):
    import odmv.io.atomic as atomic

    def save(obj, f, *a, **kw):
        Path(f).write_bytes(b"x" * 100)
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 64")

    monkeypatch.setattr(torch, "save", save)
    target = tmp_path / "a.ckpt"
    with pytest.raises(RuntimeError, match="unexpected pos"):  # room left: not a full disk
        atomic.write_atomic(target, lambda tmp: torch.save({}, tmp))
    full = shutil.disk_usage(tmp_path)._replace(free=0)
    monkeypatch.setattr(atomic.shutil, "disk_usage", lambda p: full)
    with pytest.raises(atomic.DiskFullError, match=f"{target}: no space left"):
        atomic.write_atomic(target, lambda tmp: torch.save({}, tmp))
    assert list(tmp_path.iterdir()) == []


def test_the_array_cache_on_a_real_full_disk_is_one_line_and_leaves_nothing(small_disk):
    from odmv.data.cache import ArrayCache
    from odmv.data.dataset import SampleSpec
    from odmv.io.atomic import DiskFullError

    spec = SampleSpec(_VIEWS, 64, 64, 2, 0)
    abandoned = small_disk / ".cache.999999999.tmp"  # a killed build's (no such pid)
    abandoned.mkdir()

    def load(sid):  # every array zero (broadcast into each item)
        return defaultdict(float)

    with pytest.raises(DiskFullError, match="no space left for the decoded-array cache"):
        ArrayCache.build(small_disk / "cache", [f"{i:06d}" for i in range(40)], spec, load)
    assert list(small_disk.iterdir()) == []


def test_abandoned_temporary_files_are_removed_by_the_next_write(tmp_path):
    from odmv.io.atomic import temporary, write_text

    target = tmp_path / "metrics.json"
    dead = target.with_name(f".{target.name}.999999999.tmp")
    dead.write_text("half")
    mine = temporary(target)  # this live process's own is not touched by the sweep
    write_text(target, "{}")
    assert not dead.exists() and target.read_text() == "{}"
    assert not mine.exists()


def test_simulate_on_a_full_or_read_only_disk_is_one_line(small_disk, read_only_disk, tmp_path):
    args = ["scenes=2", "resolution=64", "workers=1", "progress=false"]
    line = one_line_error(run_app("simulate", f"out={small_disk}/ds", *args, cwd=tmp_path))
    assert "are free there" in line or "no space left" in line  # said before or as it ran out
    assert not list((small_disk / "ds" / "scenes").glob("*"))  # no half-written scene
    line = one_line_error(run_app("simulate", f"out={read_only_disk}/ds", *args, cwd=tmp_path))
    assert line.startswith(f"error: {read_only_disk}/ds") and "read-only file system" in line


# ---------------------------------------------------------------- outputs never overwrite inputs
def test_predict_never_writes_into_a_dataset(trained, dataset_copy, tmp_path):
    from odmv.deploy.predict import predict
    from odmv.io.guard import OverwriteError

    ckpt = trained[1]["best_checkpoint"]
    truth = {p: p.read_bytes() for p in (dataset_copy / "scenes").glob("*/depth.exr")}
    scenes = dataset_copy / "scenes"
    for inp, out, extra in (
        (f"{scenes}/*", scenes, []),
        (scenes / "000003", scenes / "000003", []),
        (scenes / "000003", scenes / "000003", ["overwrite=true"]),
        (scenes / "000003", dataset_copy / "predictions", []),
    ):
        cfg = compose_config("predict", [f"ckpt_path={ckpt}", f"input={inp}", f"out={out}", *extra])
        with pytest.raises(OverwriteError, match=f"lies inside the dataset {dataset_copy}"):
            predict(cfg)
    assert {p: p.read_bytes() for p in truth} == truth
    assert not list(dataset_copy.rglob("predict.yaml")) and not list(dataset_copy.rglob(".hydra"))


def _capture(tiny_dataset, folder):
    """A capture folder: the network images of one twin scene as EXR files."""
    scene = tiny_dataset / "scenes" / "000004" / "fringe"
    for v in _VIEWS:
        write_exr(folder / f"{v}.exr", {"Y": read_channel(scene / f"{v}_f2_s00.exr", "Y")})
    return folder


def test_predict_writes_into_a_capture_only_when_told(trained, tiny_dataset, tmp_path):
    from odmv.deploy.predict import predict
    from odmv.io.guard import OverwriteError

    capture = _capture(tiny_dataset, tmp_path / "capture")
    ckpt = trained[1]["best_checkpoint"]
    base = [f"ckpt_path={ckpt}", f"input={capture}", f"out={capture}"]
    with pytest.raises(OverwriteError, match="is or lies inside the input"):
        predict(compose_config("predict", base))
    assert sorted(p.name for p in capture.iterdir()) == [f"{v}.exr" for v in sorted(_VIEWS)]
    predict(compose_config("predict", [*base, "overwrite=true"]))
    assert (capture / "depth.exr").is_file() and (capture / "right.exr").is_file()


def test_convert_refuses_an_output_inside_its_source_and_nan_fringes(tmp_path):
    from odmv.importers.convert import convert
    from odmv.importers.formats import ConvertError
    from odmv.io.guard import OverwriteError

    src = tmp_path / "src"
    src.mkdir()
    x = np.linspace(0, 8 * np.pi, 32)
    fringes = np.broadcast_to(0.5 + 0.4 * np.cos(x), (10, 32, 32)).astype(np.float32).copy()
    np.save(src / "Z.npy", np.full((10, 32, 32), -5.0, np.float32))
    np.save(src / "f1_80.npy", fringes)
    with pytest.raises(OverwriteError, match="is or lies inside the input"):
        convert("uhrnet", src, src / "converted")
    fringes[3, :20, :20] = np.nan
    np.save(src / "f1_80.npy", fringes)
    with pytest.raises(ConvertError, match=r"sample 3 .*400 fringe pixel\(s\) are not finite"):
        convert("uhrnet", src, tmp_path / "out")
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------- captures are checked
@pytest.mark.parametrize(
    "damage, extra, message",
    [
        ("nan", [], r"right.exr: 400 pixel\(s\) are not finite"),
        ("grey", [], r"down.exr: no fringe \(1-99 % intensities 0.500-0.500 of full scale\)"),
        ("black", [], r"down.exr: no fringe"),
        ("corrupt", [], r"left.exr: intensities down to -91.8, which no camera records"),
        (None, ["scale=0"], "scale: 0; a positive full scale"),
        (None, ["scale=-5"], "scale: -5; a positive full scale"),
        (None, ["scale=0.1"], r"lie above 1.5 times full scale .* give the camera's full scale"),
    ],
)
def test_a_capture_without_a_usable_fringe_is_refused_naming_the_file(
    damage, extra, message, trained, tiny_dataset, tmp_path
):
    from odmv.data.dataset import DataError
    from odmv.deploy.predict import predict

    capture = _capture(tiny_dataset, tmp_path / "capture")
    if damage == "nan":
        a = read_channel(capture / "right.exr", "Y")
        a[:20, :20] = np.nan
        write_exr(capture / "right.exr", {"Y": a})
    elif damage in ("grey", "black"):
        write_exr(
            capture / "down.exr",
            {"Y": np.full((64, 64), 0.5 if damage == "grey" else 0, np.float32)},
        )
    elif damage == "corrupt":
        a = read_channel(capture / "left.exr", "Y")
        a[5, 5] = -91.8
        write_exr(capture / "left.exr", {"Y": a})
    ckpt = trained[1]["best_checkpoint"]
    args = [f"ckpt_path={ckpt}", f"input={capture}", f"out={tmp_path / 'out'}", *extra]
    with pytest.raises(DataError, match=message):
        predict(compose_config("predict", args))
    assert not (tmp_path / "out" / "depth.exr").exists()


def test_a_corrupted_fringe_is_named_by_training_and_the_validator(dataset_copy, tmp_path):
    from odmv.data.dataset import DataError
    from odmv.io.validation import validate
    from odmv.training.run import train

    path = dataset_copy / "scenes" / "000002" / "fringe" / "up_f2_s00.exr"
    a = read_channel(path, "Y")
    a[3, 3] = -91.8
    write_exr(path, {"Y": a})
    problems = validate(dataset_copy).problems
    assert any("intensities down to -91.8, which no camera records" in p for p in problems)
    assert not any("intensity=auto" in p for p in problems)
    with pytest.raises(DataError, match=f"{path}: intensities down to -91.8"):
        train(compose_config("train", tiny_overrides(dataset_copy, tmp_path / "run")))


# ---------------------------------------------------------------- a run folder is one run's
def test_a_run_folder_belongs_to_one_run(trained, tiny_dataset, tmp_path):
    from odmv.training.run import train
    from odmv.training.runlock import FAILED, LOCK, RunFolderError

    finished = shutil.copytree(trained[0], tmp_path / "finished")
    before = {p: p.read_bytes() for p in finished.rglob("*") if p.is_file()}
    with pytest.raises(RunFolderError, match="holds a finished run .*resume="):
        train(compose_config("train", tiny_overrides(tiny_dataset, finished)))
    assert {p: p.read_bytes() for p in finished.rglob("*") if p.is_file()} == before
    busy = tmp_path / "busy"
    busy.mkdir()
    holder = subprocess.Popen(["sleep", "60"])
    try:
        (busy / LOCK).write_text(f"{holder.pid}\n")
        with pytest.raises(RunFolderError, match=f"another run \\(pid {holder.pid}\\)"):
            train(compose_config("train", tiny_overrides(tiny_dataset, busy)))
    finally:
        holder.kill()
        holder.wait()
    # a killed run's lock is taken over; a failing run leaves its error beside what it wrote
    bad = tiny_overrides(tiny_dataset, busy, "data.fringe_frequency=7")
    with pytest.raises(ValueError):
        train(compose_config("train", bad))
    assert (busy / FAILED).read_text().startswith(("DataError", "ValueError"))
    assert not (busy / LOCK).exists()


def test_a_refused_second_run_leaves_the_running_runs_folder_as_it_was(tiny_dataset, tmp_path):
    """A run that has written only its startup files (.hydra/, csv/, tensorboard/, run.lock)
    is another run's all the same: a second training into it is refused and removes or
    replaces nothing (it removed the folder, and replaced the first run's .hydra/)."""
    running = tmp_path / "running"
    for name in (".hydra", "csv", "tensorboard"):
        (running / name).mkdir(parents=True)
    (running / ".hydra" / "config.yaml").write_text("the first run's config\n")
    (running / "csv" / "metrics.csv").write_text("epoch\n")
    holder = subprocess.Popen(["sleep", "60"])
    try:
        (running / "run.lock").write_text(f"{holder.pid}\n")
        before = {p: p.read_bytes() for p in running.rglob("*") if p.is_file()}
        args = [*tiny_overrides(tiny_dataset, running), "hydra.run.dir=hydra"]
        line = one_line_error(run_app("train", *args, cwd=tmp_path))
        assert f"another run (pid {holder.pid}) is writing into it" in line
        assert {p: p.read_bytes() for p in running.rglob("*") if p.is_file()} == before
        assert not (tmp_path / "hydra").exists()  # the refused run's own folder is gone
    finally:
        holder.kill()
        holder.wait()


def test_ckpt_path_never_trains_a_finished_run_again_nor_writes_elsewhere(
    trained, tiny_dataset, tmp_path
):
    """ckpt_path= of a finished run's checkpoint is refused (it retrained that run in place,
    ignoring paths.output_dir); of an unfinished run's, with another folder named, too."""
    finished = shutil.copytree(trained[0], tmp_path / "finished")
    before = {p: p.read_bytes() for p in finished.rglob("*") if p.is_file()}
    new = tmp_path / "new"
    last = finished / "checkpoints" / "last.ckpt"
    args = [*tiny_overrides(tiny_dataset, new), f"ckpt_path={last}", "hydra.run.dir=hydra"]
    line = one_line_error(run_app("train", *args, cwd=tmp_path))
    assert "holds a finished run" in line and f"init_from={finished}" in line
    assert {p: p.read_bytes() for p in finished.rglob("*") if p.is_file()} == before
    assert not new.exists() and not (tmp_path / "hydra").exists()
    (finished / "metrics.json").unlink()  # an interrupted run: continued in its own folder only
    line = one_line_error(run_app("train", *args, cwd=tmp_path))
    assert f"continues the run in {finished}" in line and f"resume={finished}" in line
    assert not new.exists() and not (finished / "failed.txt").exists()


def test_a_failed_run_leaves_no_empty_folder_and_a_corrected_rerun_gets_its_own_config(
    tiny_dataset, tmp_path
):
    out = tmp_path / "run"
    args = [*tiny_overrides(tiny_dataset, out), "hydra.run.dir=hydra"]
    one_line_error(run_app("train", *args, "data.fringe_frequency=7", cwd=tmp_path))
    assert not out.exists() and not (tmp_path / "hydra").exists()
    (out / ".hydra").mkdir(parents=True)  # a failed run's stale config
    (out / ".hydra" / "config.yaml").write_text("stale: true\n")
    done = run_app("train", *args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "stale: true" not in (out / ".hydra" / "config.yaml").read_text()


# ---------------------------------------------------------------- resume is the same run
def _last_weights(run: Path) -> dict:
    return torch.load(run / "checkpoints" / "last.ckpt", weights_only=True)["state_dict"]


def test_kill_9_then_resume_gives_the_uninterrupted_runs_weights(tiny_dataset, tmp_path):
    common = [
        *tiny_overrides(tiny_dataset, tmp_path / "x"),
        "trainer.max_epochs=4",
        "trainer.limit_train_batches=4",
        "threads=1",
    ]

    def args(out):
        return [a for a in common if not a.startswith(("paths.output_dir", "data.cache_dir"))] + [
            f"paths.output_dir={out}",
            f"data.cache_dir={tmp_path}/cache",
            f"hydra.run.dir={out}",
        ]

    whole = tmp_path / "whole"
    assert run_app("train", *args(whole), "test=false", cwd=tmp_path).returncode == 0
    killed = tmp_path / "killed"
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.Popen(
        [PY, "-m", "odmv.train", *args(killed), "test=false"],
        cwd=tmp_path,
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    last = killed / "checkpoints" / "last.ckpt"
    while not last.exists() and proc.poll() is None:
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    epoch = torch.load(last, weights_only=True)["epoch"]
    assert epoch < 3, "the run ended before it could be killed"
    resumed = run_app("train", f"resume={killed}", "hydra.output_subdir=null", cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    a, b = _last_weights(whole), _last_weights(killed)
    assert a.keys() == b.keys()
    assert all(torch.equal(a[k], b[k]) for k in a)


# ---------------------------------------------------------------- simulate's workers
def _children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


@pytest.mark.skipif(sys.platform != "linux", reason="the parent-death signal is Linux's")
def test_simulates_workers_die_with_it(tmp_path):
    proc = subprocess.Popen(
        [PY, "-m", "odmv.simulate", "out=ds", "scenes=40", "resolution=128", "workers=2"],
        cwd=tmp_path,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    scenes, deadline = tmp_path / "ds" / "scenes", time.time() + 300
    while not (scenes.is_dir() and any(scenes.iterdir())):  # a worker renders its first scene
        assert time.time() < deadline and proc.poll() is None, "the workers never started"
        time.sleep(0.2)
    workers = _children(proc.pid)
    assert len(workers) >= 2
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 10
    while any(Path(f"/proc/{p}").exists() and not zombie(p) for p in workers):
        assert time.time() < deadline, "workers outlived their parent"
        time.sleep(0.1)


def test_an_output_folder_that_is_a_file_is_one_line(trained, tmp_path):
    (tmp_path / "afile").write_text("mine\n")
    ckpt = trained[1]["best_checkpoint"]
    line = one_line_error(run_app("export", f"ckpt_path={ckpt}", "out=afile", cwd=tmp_path))
    assert line.startswith("error: afile: a file stands where a folder belongs; choose another")
    assert (tmp_path / "afile").read_text() == "mine\n"


def _fill(disk: Path) -> None:
    with (disk / "filler").open("wb") as fh:
        try:
            while True:
                fh.write(b"\0" * 65536)
                fh.flush()
        except OSError:
            pass


def test_hydra_writing_onto_a_full_or_read_only_disk_is_one_line(
    small_disk, read_only_disk, tiny_dataset, tmp_path
):
    _fill(small_disk)
    for disk, problem in ((small_disk, "no space left"), (read_only_disk, "read-only")):
        run = disk / "run"
        args = [*tiny_overrides(tiny_dataset, run), f"hydra.run.dir={run}"]
        line = one_line_error(run_app("train", *args, cwd=tmp_path))
        assert problem in line.lower() and str(disk) in line


@pytest.mark.parametrize(
    "sig, status, name", [(signal.SIGTERM, 143, "SIGTERM"), (signal.SIGINT, 130, "Ctrl-C")]
)
def test_a_signal_stops_a_training_with_its_status_and_says_how_to_resume(
    sig, status, name, tiny_dataset, tmp_path
):
    run = tmp_path / "run"
    args = [*tiny_overrides(tiny_dataset, run), "trainer.max_epochs=200"]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.Popen(
        [PY, "-m", "odmv.train", *args],
        cwd=tmp_path,
        env=env,
        stderr=subprocess.PIPE,
        text=True,
        # a shell's background job ignores SIGINT, and its children would inherit that
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    last = run / "checkpoints" / "last.ckpt"
    while not last.exists() and proc.poll() is None:
        time.sleep(0.05)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err[-2000:]
    line = err.strip().splitlines()[-1]
    assert line.startswith(f"error: {run}: stopped by {name} in epoch ")
    assert f"resume={run} continues" in line
    assert torch.load(last, weights_only=True)["epoch"] >= 0  # the last epoch's, whole
    assert not (run / "run.lock").exists() and "Interrupted" in (run / "failed.txt").read_text()
    assert not (tmp_path / "outputs").exists()  # no .hydra-only folder of Hydra's left behind
