"""Checkpoints: written whole beside their target, read with one-line errors that name the file
and what is wrong.

odmv's checkpoints hold plain data only, so they load with torch's ``weights_only``; a file
that needs more was written by another program, and torch's advice to turn the check off
never reaches the user.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from lightning.fabric.utilities.types import _PATH
from lightning.pytorch.plugins.io import TorchCheckpointIO

from odmv.io.atomic import write_atomic
from odmv.io.runfolder import METRICS


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's checkpoint writer, writing beside the target and renaming: its own writes a
    temporary file in /tmp and moves it, which on another file system is a copy that a full
    disk truncates, leaving half a checkpoint where resume and evaluate look. A full disk is a
    one-line :class:`odmv.io.atomic.DiskFullError` and the previous checkpoint stays."""

    def save_checkpoint(self, checkpoint: dict, path: _PATH, storage_options=None) -> None:
        if "://" in str(path):  # a remote store (fsspec) renames nothing: Lightning's own way
            return super().save_checkpoint(checkpoint, path, storage_options)
        write_atomic(path, lambda tmp: torch.save(checkpoint, tmp))


class CheckpointError(ValueError):
    """A checkpoint is missing, unreadable, foreign, or does not fit the net of this run."""


def read_checkpoint(path: str | Path) -> dict:
    """The checkpoint dict at ``path`` (on the CPU), checked to be one odmv wrote."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # torch raises RuntimeError, OSError, EOFError or UnpicklingError
        if "Unsupported global" in str(e):  # readable, but only by running foreign code
            raise CheckpointError(
                f"{path}: holds Python objects besides tensors and plain data; odmv "
                "checkpoints never do (written by another program?)"
            ) from None
        raise CheckpointError(f"{path}: not a PyTorch checkpoint, or truncated") from None
    hparams = ckpt.get("hyper_parameters") if isinstance(ckpt, dict) else None
    if not isinstance(hparams, dict) or "net_cfg" not in hparams or "state_dict" not in ckpt:
        raise CheckpointError(f"{path}: not an odmv checkpoint (no net settings and weights)")
    return ckpt


def _setting_differences(saved: dict, current: dict) -> list[str]:
    keys = [k for k in dict.fromkeys([*saved, *current]) if saved.get(k) != current.get(k)]
    return [f"{k} {saved.get(k)!r} (this run {current.get(k)!r})" for k in keys]


def best_checkpoint(run: Path) -> tuple[Path, dict]:
    """A finished run's best checkpoint (recorded relative to the run folder; an older record's
    absolute path is looked for beside the run where the folder was moved) and its
    metrics.json."""
    path = run / METRICS
    if not path.is_file():
        raise CheckpointError(f"{run}: no {METRICS} (not a finished run)")
    metrics = json.loads(path.read_text())
    ckpt = run / metrics["best_checkpoint"]  # relative to the run folder, or absolute (older)
    if not ckpt.is_file():
        ckpt = run / "checkpoints" / ckpt.name  # the run folder was moved
    return ckpt, metrics


def checkpoint_path(source: str | Path) -> Path:
    """A checkpoint named directly, or a finished run folder's best checkpoint."""
    path = Path(source)
    return best_checkpoint(path)[0] if path.is_dir() else path


def initial_weights(source: str | Path, current: dict) -> dict:
    """The weights a run starts from (``init_from``): those of checkpoint ``source``, or of a
    finished run folder's best checkpoint, checked to fit the net's ``current`` state dict by
    name and shape. Other settings may differ (a fine-tune changes data, views available or
    epochs); its epoch, optimizer and scheduler state are not taken."""
    path = checkpoint_path(source)
    ckpt = read_checkpoint(path)
    check_weights(path, ckpt["state_dict"], current)
    return ckpt["state_dict"]


def check_fits(path: str | Path, ckpt: dict, net_cfg: dict, views: list[str]) -> None:
    """Refuse to continue from a checkpoint of another net or view set, naming what differs."""
    hp = ckpt["hyper_parameters"]
    differences = _setting_differences(hp["net_cfg"], net_cfg)
    if hp.get("views") is not None and list(hp["views"]) != list(views):
        differences.append(f"views {','.join(hp['views'])} (this run {','.join(views)})")
    if differences:
        raise CheckpointError(f"{path}: trained with {'; '.join(differences)}")


def check_weights(path: str | Path, saved: dict, current: dict) -> None:
    """Refuse weights whose names or shapes differ from the net's, naming the first few."""
    missing = [k for k in current if k not in saved]
    extra = [k for k in saved if k not in current]
    shapes = [
        f"{k} {tuple(saved[k].shape)} vs {tuple(v.shape)}"
        for k, v in current.items()
        if k in saved and saved[k].shape != v.shape
    ]
    if missing or extra or shapes:
        parts = [
            f"{len(items)} {what}: {', '.join(items[:2])}{', ...' if len(items) > 2 else ''}"
            for what, items in (
                ("missing", missing),
                ("unexpected", extra),
                ("of other shape", shapes),
            )
            if items
        ]
        raise CheckpointError(f"{path}: weights do not fit the net ({'; '.join(parts)})")
