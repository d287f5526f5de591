"""experiments/gpu_check.sh, the device check, runs through on a machine without CUDA: every
step at a tiny size, each step's output and exit status written where it was told."""

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.slow
@pytest.mark.skipif(torch.cuda.is_available(), reason="the tiny run is for machines without CUDA")
def test_the_gpu_check_runs_every_step_tiny_without_cuda(tmp_path):
    env = os.environ | {"PYTHON": sys.executable}
    done = subprocess.run(
        ["bash", str(ROOT / "experiments" / "gpu_check.sh"), str(tmp_path)],
        capture_output=True, text=True, timeout=900, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-2000:]
    assert "no CUDA device: every step at a tiny size" in done.stdout
    summary = (tmp_path / "summary.txt").read_text().splitlines()
    steps = [line.split()[0] for line in summary]
    assert steps == [
        "environment", "bf16", "train_quickstart", "infer", "infer_lite", "render", "train_steps",
        "loss_curve",
    ]  # fmt: skip
    assert all(" rc=0 " in line for line in summary)
    assert "bf16-mixed" in (tmp_path / "bf16.txt").read_text()
    assert "ms/frame p50" in (tmp_path / "infer.txt").read_text()
    assert "odmvnet_lite" in (tmp_path / "infer_lite.txt").read_text()
    curve = (tmp_path / "loss_curve.txt").read_text().splitlines()
    assert [line.split()[:2] for line in curve] == [["step", "0"], ["step", "1"], ["step", "2"]]
