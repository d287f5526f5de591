"""Where a result comes from: the code's commit, the machine, the time and the dataset's
fingerprint, recorded with each run so a report rebuilt from its records says the same."""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
from datetime import datetime, timezone
from pathlib import Path

from odmv.io.manifest import MANIFEST

CHECKOUT = Path(__file__).resolve().parent.parent


def _git(root: Path, *args: str) -> str:
    done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True)
    if done.returncode:
        raise OSError(done.stderr.strip())
    return done.stdout.strip()


#: where runs write their records (a reproduction updates them while it runs): no code
RESULTS = "experiments/results"


def commit(root: Path = CHECKOUT) -> str:
    """The commit of the checkout at ``root`` (odmv's own by default), marked where tracked
    files other than result records differ from it."""
    try:
        sha = _git(root, "rev-parse", "--short", "HEAD")
        dirty = _git(
            root, "status", "--porcelain", "--untracked-files=no", "--", ".", f":!{RESULTS}"
        )
    except OSError:
        return "unknown (not a git checkout)"
    return sha + (" (with uncommitted changes)" if dirty else "")


def machine() -> str:
    import torch

    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU"
    return (
        f"{platform.machine()}, {os.cpu_count()} CPU cores, {gpu}; Python "
        f"{platform.python_version()}, torch {torch.__version__}"
    )


def utc_now() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")


def manifest_sha1(dataset: str | Path) -> str | None:
    """The first 12 hex digits of the SHA-1 of a dataset's manifest; None where it is not on
    disk."""
    manifest = Path(dataset) / MANIFEST
    return hashlib.sha1(manifest.read_bytes()).hexdigest()[:12] if manifest.is_file() else None


def provenance(dataset: str | Path) -> dict[str, str | None]:
    """The fields a finished run records beside its metrics: its dataset (absolute) with the
    manifest's fingerprint, the commit, the machine and when it finished."""
    return {
        "dataset": str(Path(dataset).resolve()),
        "dataset_sha1": manifest_sha1(dataset),
        "commit": commit(),
        "machine": machine(),
        "finished": utc_now(),
    }


#: config keys that say where or how fast a run went, not what it trained: its seed and thread
#: count (a row's repeats), paths, logging, progress, testing, memory and kernel choices, the
#: dataset's settings (its fingerprint stands for them) and the per-net tables that the chosen
#: net's keys resolve
NOT_SETUP = (
    "seed", "seeds", "threads", "paths", "hydra", "logger", "callbacks", "root", "resume",
    "ckpt_path", "task_name", "test", "log_images", "optimized_metric",
    "contenders", "widths", "alphas", "lrs", "compile", "data.root", "data.cache",
    "data.cache_dir", "data.num_workers", "data.progress", "data.render", "data.simulate",
    "data.eval_batch_size", "trainer.default_root_dir", "trainer.enable_progress_bar",
    "trainer.enable_model_summary", "trainer.log_every_n_steps", "trainer.accelerator",
    "trainer.devices", "trainer.num_sanity_val_steps", "trainer.limit_val_batches",
    "trainer.limit_test_batches", "trainer.deterministic", "model.table2", "model.display",
    "model.net.memory_format", "model.net.activation_checkpointing", "optimizer.fused",
)  # fmt: skip
#: runs that start from another run's weights: which run is a path (seed-named, moved with
#: the records), so the setup says only that one was given
GIVEN = ("init_from", "distill_from")


def training_setup(cfg) -> dict[str, str]:
    """What a run trained, as ``dotted.key -> value`` of its resolved config without
    :data:`NOT_SETUP`: two runs with equal setups and datasets are seeds of one row
    (odmv.study.results), any other pair is not."""
    from omegaconf import OmegaConf

    def leaves(node, prefix: str):
        if isinstance(node, dict):
            for k, v in node.items():
                yield from leaves(v, f"{prefix}{k}.")
        else:
            yield prefix[:-1], node

    skipped = tuple(f"{k}." for k in NOT_SETUP)
    setup = {}
    for key, _ in leaves(OmegaConf.to_container(cfg, resolve=False), ""):
        if key in NOT_SETUP or key.startswith(skipped):
            continue
        value = OmegaConf.select(cfg, key, throw_on_resolution_failure=False)
        if key in GIVEN:
            value = "given" if value else None
        elif OmegaConf.is_config(value):
            value = OmegaConf.to_container(value, resolve=True)  # a list
        setup[key] = json.dumps(value) if isinstance(value, list) else str(value)
    return dict(sorted(setup.items()))
