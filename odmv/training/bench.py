"""What the benchmark scripts (experiments/bench_train.py, bench_infer.py, bench_convs.py) share:
a net built from a preset's config exactly as training builds it, a synthetic batch of the real
shapes (random values: speed and memory do not depend on them), and the timing loop."""

from __future__ import annotations

import resource
import time

import torch
from omegaconf import DictConfig

from odmv.config import CONF_DIR  # (and registers the config resolvers)
from odmv.data.normalize import Normalization
from odmv.data.reference import view_channels
from odmv.rig import Rig, size_hw
from odmv.training.module import FPPModule

PRESETS = ("paper", "paper_plus", "mini", "quickstart")


def preset_config(preset: str, model: str, overrides: list[str] = ()) -> DictConfig:
    """The training config of ``experiment=preset model=model`` plus ``overrides``."""
    from hydra import compose, initialize_config_dir

    if preset not in PRESETS:
        raise ValueError(f"--preset {preset!r}: choose one of {', '.join(PRESETS)}")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(
            "train",
            [f"experiment={preset}", f"model={model}", "paths.output_dir=.", *overrides],
        )


def input_size(cfg: DictConfig) -> tuple[int, int]:
    return size_hw(cfg.data.resolution)


def build_module(cfg: DictConfig) -> FPPModule:
    """The module training would build (net, loss weights), with the twin's normalization."""
    norm = Normalization.for_working_distance(
        Rig().camera.working_distance_mm,
        cfg.data.depth_half_range_mm,
        1.0,
        cfg.data.depth_target,
    )
    return FPPModule.from_config(cfg, norm.to_dict(), list(cfg.data.views))


def synthetic_batch(cfg: DictConfig, batch: int, device: torch.device) -> dict:
    """A batch with every key the composite loss may read, at the config's sizes."""
    h, w = input_size(cfg)
    s = len(cfg.data.views)
    vc = view_channels(cfg.data.reference)
    g = torch.Generator().manual_seed(0)

    def rand(*shape):
        return torch.rand(*shape, generator=g).to(device)

    out = {
        "fringes": rand(batch, s, h, w) * 2 - 1,
        "depth": rand(batch, 1, h, w) * 2 - 1,
        "lit": (rand(batch, s, h, w) > 0.2).float(),
        "phase_target": rand(batch, 2 * s, h, w) * 2 - 1,
        "scene_id": [f"{i:06d}" for i in range(batch)],
    }
    if vc > 1:
        out["inputs"] = rand(batch, s * vc, h, w) * 2 - 1
    return out


def peak_memory(device: torch.device) -> str:
    """CUDA: the most memory tensors held; CPU: the process's peak resident set."""
    if device.type == "cuda":
        return f"{torch.cuda.max_memory_allocated(device) / 2**30:.2f} GiB peak allocated"
    return f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB peak RSS"


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(run, repeats: int, warmup: int, device: torch.device) -> list[float]:
    """Seconds of each of ``repeats`` calls of ``run`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        run()
    sync(device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        sync(device)
        times.append(time.perf_counter() - t0)
    return times


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q / 100 * (len(ordered) - 1)))]
