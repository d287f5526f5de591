"""The demo's closing lines: the commands that continue from its run, each run as printed."""

import shlex
import shutil
import subprocess
from pathlib import Path

from odmv.training.run import next_steps


def test_the_commands_the_demo_prints_work_as_printed(trained, tmp_path):
    run = shutil.copytree(trained[0], tmp_path / "outputs" / "demo" / "2026-12-06_08-00-00")
    ckpt = run / "checkpoints" / Path(trained[1]["best_checkpoint"]).name
    lines = next_steps(run, ckpt)
    assert [line.split()[2] for line in lines] == [
        "odmv.predict",
        "odmv.evaluate",
        "odmv.export",
        "odmv.report",
    ]
    for line in lines:
        args = shlex.split(line)
        args[0] = str(Path(args[0]).absolute()) if Path(args[0]).exists() else args[0]
        done = subprocess.run(args, cwd=tmp_path, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, f"{line}\n{done.stderr[-2000:]}"
    assert (run / "prediction" / "depth.exr").is_file()
    assert (run / "onnx" / "model.onnx").is_file()
    assert (run / "report" / "tables.md").is_file()
    for made in ("prediction", "report"):  # each writes its offline page
        assert "Plotly.newPlot" in (run / made / "page.html").read_text()


def test_the_demo_says_how_it_is_used_and_chooses_its_threads(monkeypatch, tmp_path):
    """--help prints its use (no Hydra traceback); the threads it trains with are one per core
    other work leaves free."""
    from helpers import run_app

    from odmv.training import pace

    done = run_app("demo", "--help", cwd=tmp_path)
    assert done.returncode == 0 and "threads=N" in done.stdout, done.stderr[-2000:]
    monkeypatch.setattr(pace.os, "cpu_count", lambda: 2)
    for busy, threads in ((0.1, 2), (1.0, 1), (1.9, 1)):
        monkeypatch.setattr(pace, "busy_cores", lambda b=busy: b)
        assert pace.free_threads()[0] == threads
    assert pace.busy_cores_note(1) is None  # one thread: nothing fewer to advise
