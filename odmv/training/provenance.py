"""Where a result comes from: the code's commit, the machine, the time and the dataset's
fingerprint, recorded with each run so a report rebuilt from its records says the same."""

from __future__ import annotations

import hashlib
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
