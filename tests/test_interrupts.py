"""Every app stopped midway (Ctrl-C to its process group as a terminal sends it, SIGTERM as a
scheduler does, ``kill -9`` of a parent) leaves the old output or nothing, says so in one line
and exits with the signal's status."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import zombie

PY = sys.executable


def _start(args, cwd) -> subprocess.Popen:
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.Popen(
        [PY, "-m", *args],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as a terminal's foreground job
        # a shell's background job ignores SIGINT, and its children would inherit that
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def _wait_for(proc: subprocess.Popen, text: str, timeout: float = 120) -> None:
    """Read the app's stdout until a line holds ``text``."""
    deadline = time.time() + timeout
    for line in proc.stdout:
        if text in line:
            return
        assert time.time() < deadline, f"never printed {text!r}"
    pytest.fail(f"exited ({proc.wait()}) before printing {text!r}: {proc.stderr.read()[-2000:]}")


def _stopped(proc: subprocess.Popen, sig: int, status: int, name: str) -> None:
    os.killpg(proc.pid, sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == status, err[-2000:]
    assert "Traceback" not in err, err[-3000:]
    assert err.strip().splitlines()[-1].startswith(f"error: stopped by {name}; no file"), err


@pytest.mark.parametrize(
    "sig, status, name", [(signal.SIGINT, 130, "Ctrl-C"), (signal.SIGTERM, 143, "SIGTERM")]
)
def test_an_export_stopped_midway_leaves_the_old_set_as_it_was(
    sig, status, name, trained, tmp_path
):
    out = tmp_path / "exported"
    out.mkdir()
    old = {"model.onnx": b"old graph", "rig.npz": b"old rig", "notes.txt": b"mine"}
    for file, data in old.items():
        (out / file).write_bytes(data)
    ckpt = trained[1]["best_checkpoint"]
    proc = _start(["odmv.export", f"ckpt_path={ckpt}", f"out={out}"], tmp_path)
    _wait_for(proc, "exporting the graph")
    _stopped(proc, sig, status, name)
    assert {p.name: p.read_bytes() for p in out.iterdir()} == old
    assert [p.name for p in tmp_path.iterdir()] == ["exported"]  # no staging folder left


def test_an_export_replaces_the_whole_set(trained, tmp_path):
    """A float32 export into the folder of an int8 one removes the old int8 graph: a set never
    mixes two exports."""
    out = tmp_path / "exported"
    out.mkdir()
    (out / "model.int8.onnx").write_bytes(b"an older export's")
    ckpt = trained[1]["best_checkpoint"]
    done = subprocess.run(
        [PY, "-m", "odmv.export", f"ckpt_path={ckpt}", f"out={out}"],
        cwd=tmp_path, capture_output=True, text=True,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == ["model.onnx", "rig.npz"]


@pytest.mark.parametrize(
    "sig, status, name", [(signal.SIGINT, 130, "Ctrl-C"), (signal.SIGTERM, 143, "SIGTERM")]
)
def test_simulate_stopped_is_one_line_and_a_rerun_finishes_it(sig, status, name, tmp_path):
    args = ["odmv.simulate", "out=ds", "scenes=12", "resolution=64", "workers=2", "progress=false"]
    proc = _start(args, tmp_path)
    scenes, deadline = tmp_path / "ds" / "scenes", time.time() + 300
    while not (scenes.is_dir() and any(p.name.startswith(".partial") for p in scenes.iterdir())):
        assert time.time() < deadline and proc.poll() is None, "no scene was ever started"
        time.sleep(0.05)
    _stopped(proc, sig, status, name)
    done = subprocess.run([PY, "-m", *args], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "ds: ok, 12 scenes" in done.stdout


@pytest.mark.skipif(sys.platform != "linux", reason="the parent-death signal is Linux's")
def test_a_study_s_training_child_ends_with_a_killed_parent(tmp_path):
    """odmv.reproduce and the adaptation study run each training through run_child: kill -9 of
    the parent must not leave it writing on (a rerun would race with it)."""
    marker = tmp_path / "child.pid"
    child_code = (
        f"import os, time; open({str(marker)!r}, 'w').write(str(os.getpid())); time.sleep(300)"
    )
    parent_code = (
        "import sys\n"
        "from odmv.io.processes import run_child\n"
        f"run_child([sys.executable, '-c', {child_code!r}], sys.stdout)\n"
    )
    parent = subprocess.Popen([PY, "-c", parent_code])
    deadline = time.time() + 60
    while not (marker.is_file() and marker.read_text()):
        assert time.time() < deadline and parent.poll() is None, "the child never started"
        time.sleep(0.05)
    child = int(marker.read_text())
    parent.send_signal(signal.SIGKILL)
    parent.wait()
    deadline = time.time() + 10
    while Path(f"/proc/{child}").exists() and not zombie(child):
        assert time.time() < deadline, "the child outlived its killed parent"
        time.sleep(0.05)


@pytest.mark.slow
def test_a_training_stopped_while_it_renders_its_dataset_offers_no_resume(tmp_path):
    """Ctrl-C before the first epoch: no checkpoint to resume from, and the message says so
    (not resume=RUN for a folder that is then removed); the same command then finishes."""
    args = ["odmv.train", "experiment=quickstart", "data.simulate.scenes=24",
            "data.simulate.resolution=32", "data.resolution=32", "data.simulate.workers=1",
            "trainer.max_epochs=1", "trainer.limit_train_batches=2", "model.net.blocks=1",
            "trainer.enable_progress_bar=false", "data.progress=false", "paths.output_dir=run",
            "log_images=0"]  # fmt: skip
    proc = _start(args, tmp_path)
    deadline = time.time() + 300
    while not any(p.name.startswith(".partial") for p in tmp_path.glob("data/*/scenes/*")):
        assert time.time() < deadline and proc.poll() is None, "no scene was ever started"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "Traceback" not in err, err[-3000:]
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: stopped by Ctrl-C before the first epoch ended") and (
        "resume=" not in line
    ), line
    done = subprocess.run([PY, "-m", *args], cwd=tmp_path, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "run" / "metrics.json").is_file()
    # a log, not a terminal: one line an epoch and one line of test figures, no Lightning bars,
    # tables or tips
    out = done.stdout + done.stderr
    assert "epoch 1/1: val MAE " in out and "  test: MAE " in out and "metrics.json" in out
    for noise in ("Epoch 0/", "Test metric", "GPU available", "Tip:", "LeafSpec"):
        assert noise not in out, noise
