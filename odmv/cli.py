"""How every app reports a fault: one line, ``error: <file or key>: <problem>``, exit status 2,
and no empty run folder left behind. ``HYDRA_FULL_ERROR=1`` shows the traceback.

The project's errors (DataError, ManifestError, ExrError, SimulationError, ...) are
ValueErrors that name the file or config key at fault; one raised by a config resolver or a
constructor arrives wrapped by OmegaConf or Hydra and is reported by its own message. The
operating system's (a full disk, a read-only folder, a file where a folder belongs) name the
file from the OSError. Hydra's own (an unknown config option, a key typo, a ``.hydra`` folder it
cannot write) are put in one line by :func:`odmv.config.app`, which every entry point uses
instead of ``hydra.main``.
"""

from __future__ import annotations

import difflib
import errno
import logging
import os
import re
import shutil
import signal
import sys
import threading
import warnings
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

from hydra.errors import InstantiationException
from lightning.pytorch.utilities import rank_zero_only
from omegaconf.errors import OmegaConfBaseException

from odmv.io.atomic import DISK_FULL
from odmv.io.runfolder import FAILED, LOCK, lock_holder

T = TypeVar("T")

#: What Hydra and the loggers write into a run folder before the first checkpoint; a folder
#: holding only these belongs to a run that failed before it produced anything.
_STARTUP_FILES = {
    ".hydra",
    "train.log",
    "evaluate.log",
    "predict.log",
    "predict.yaml",
    "csv",
    "tensorboard",
    LOCK,
    FAILED,
}


WRAPPERS = (OmegaConfBaseException, InstantiationException)


def one_line(exc: BaseException, where: str | os.PathLike | None = None) -> str:
    from hydra.errors import MissingConfigException

    if isinstance(exc, MissingConfigException):  # an OSError too, for Hydra
        return hydra_line(exc)
    if isinstance(exc, OSError):
        return os_line(exc, where)
    key = None
    while isinstance(exc, WRAPPERS) and exc.__cause__ is not None:
        key = key or getattr(exc, "full_key", None)
        exc = exc.__cause__  # the resolver's or constructor's own message, not the wrapper
    text = str(exc).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    # OmegaConf words a resolver's error as "<Type> raised while resolving interpolation: ..."
    line = re.sub(r"^\w+ raised while resolving interpolation: ", "", line)
    key = key or getattr(exc, "full_key", None)
    return f"{key}: {line}" if key and not line.startswith(f"{key}:") else line


def os_line(exc: OSError, where: str | os.PathLike | None = None) -> str:
    """``<file>: <problem>`` for an OSError; a full disk also says what to do."""
    name = exc.filename or where
    problem = exc.strerror or str(exc) or type(exc).__name__
    if exc.errno in DISK_FULL:
        problem = "no space left on the device; free some, or write elsewhere"
    elif exc.errno in (errno.EEXIST, errno.ENOTDIR):
        problem = "a file stands where a folder belongs; choose another out= or move the file"
    elif exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
        problem = f"{problem.lower()}; write elsewhere (out= or paths.output_dir=)"
    return f"{name}: {problem}" if name else problem


def quiet_lightning() -> None:
    """Lightning's info chatter (tips to install its cloud products, "GPU available: False",
    "was configured so 1 batch per epoch will be used") drowns what the apps print; its
    warnings still show."""
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # Lightning's own pytree helper builds torch's deprecated LeafSpec; nothing a user can act on
    warnings.filterwarnings("ignore", message=r".*isinstance\(treespec, LeafSpec\)")
    # the training loss is logged per epoch too, so an epoch shorter than the step interval
    # still draws its curve (train/loss_epoch, odmv.training.module.FPPModule.training_step)
    warnings.filterwarnings("ignore", message=r"The number of training batches .* logging interval")
    # a resumed run's folder holds its checkpoints by design (a new run's is refused before)
    warnings.filterwarnings("ignore", message=r"Checkpoint directory .* exists and is not empty")
    # bf16-mixed keeps the weights in float32, so the summary's 32-bit size is the right one
    warnings.filterwarnings("ignore", message=r"Precision bf16-mixed is not supported by the model")


def tool(name: str) -> str:
    """A command that runs this environment's console script ``name`` as printed, venv
    activated or not: its path beside the interpreter (relative under the current folder)."""
    path = Path(sys.executable).parent / name
    if not path.is_file():
        return name
    try:
        return str(path.relative_to(Path.cwd()))
    except ValueError:
        return str(path)


#: output folders the command line named that existed before the command ran: the user's
_EXISTING: set[Path] = set()
_OUTPUT_KEYS = ("out", "paths.output_dir", "hydra.run.dir")


def note_existing_outputs(argv: list[str]) -> None:
    """Remember which output folders named on the command line exist already (before Hydra
    creates its run folder), so that a failure removes only folders the command created."""
    for arg in argv:
        key, _, value = arg.lstrip("+~").partition("=")
        if key in _OUTPUT_KEYS and value and Path(value).is_dir():
            _EXISTING.add(Path(value).resolve())


def remove_if_empty(folder: Path | None) -> None:
    """Delete a run folder that holds nothing but what every run writes at its start, unless
    the command did not create it (a folder the user had, or one another live training holds:
    a refused second run must not remove the first's)."""
    if folder is None or not folder.is_dir() or lock_holder(folder) is not None:
        return
    if folder.resolve() in _EXISTING:
        return
    if all(p.name in _STARTUP_FILES or _empty_folder(p) for p in folder.iterdir()):
        shutil.rmtree(folder, ignore_errors=True)
        here = Path.cwd().resolve()
        for parent in folder.resolve().parents:  # outputs/<task>/ left empty by it
            if parent == here or here not in parent.parents or any(parent.iterdir()):
                break
            parent.rmdir()


def _empty_folder(path: Path) -> bool:
    return path.is_dir() and not any(path.iterdir())


class Interrupted(Exception):
    """A run stopped by a signal (Ctrl-C, or SIGTERM from a scheduler or ``kill``): one line
    naming what was stopped and what it left, and the shell's status for that signal (128 + its
    number), so a script or SLURM does not count the run as finished."""

    def __init__(self, message: str, signal_number: int):
        super().__init__(message)
        self.exit_status = 128 + signal_number


#: what every app but a training's fit leaves when stopped: its files are written whole
#: (odmv.io.atomic) or staged and moved into place together (export), so a rerun finishes it
STOPPED = "no file was left half-written; run the command again to finish"

_deferred = False  # a handler of its own takes SIGTERM (a training's fit: Lightning's)
_terminated = False  # SIGTERM arrived: whatever a library wrapped the stop in, it is a stop


@contextmanager
def sigterm_deferred():
    """Within, SIGTERM is left to the code that runs (Lightning stops a fit at a step's end and
    the app says how to resume); outside, :func:`run_app` stops the app at once."""
    global _deferred
    before, _deferred = _deferred, True
    try:
        yield
    finally:
        _deferred = before


def _stop_on_sigterm(signum, frame) -> None:
    global _terminated
    if not _deferred:
        _terminated = True
        raise _sigterm_stop()


def _sigterm_stop() -> Interrupted:
    return Interrupted(f"stopped by SIGTERM; {STOPPED}", signal.SIGTERM)


def _catch_sigterm() -> None:
    """Turn SIGTERM into :class:`Interrupted`, so the app's ``finally`` clauses and staged
    writes clean up as they do on Ctrl-C (the default action ends the process on the spot)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _stop_on_sigterm)


@dataclass(frozen=True)
class JobFailed:
    """What a multirun job's app returns instead of exiting: the sweep goes on with its other
    jobs, odmv.training.sweep writes ``error`` into the job's results.csv row and exits with 2
    at the end."""

    error: str


def run_app(
    fn: Callable[[], T], run_dir: str | os.PathLike | list[Path] | None = None
) -> T | JobFailed:
    """Run an app's body; on one of the project's errors print one line and exit with 2
    (in a multirun: return JobFailed). ``run_dir``: the run folder(s) to remove if the failed
    run left them empty (a list may grow while the body runs)."""
    quiet_lightning()
    _catch_sigterm()
    try:
        try:
            return fn()
        except KeyboardInterrupt:
            raise Interrupted(f"stopped by Ctrl-C; {STOPPED}", signal.SIGINT) from None
        except Exception as exc:  # (the ONNX exporter wraps the stop in an error of its own)
            if _terminated and not isinstance(exc, Interrupted):
                raise _sigterm_stop() from None
            raise
    except (ValueError, OSError, Interrupted, *WRAPPERS) as exc:
        if traceback_wanted():
            raise
        folders = run_dir if isinstance(run_dir, list) else [run_dir] if run_dir else []
        where = folders[-1] if folders else None
        line = one_line(exc, where)
        if rank_zero_only.rank == 0:  # DDP ranks fail alike; one line is enough
            print(f"error: {line}", file=sys.stderr)
        for folder in folders:
            remove_if_empty(Path(folder))
        if in_multirun():
            return JobFailed(line)
        sys.exit(getattr(exc, "exit_status", 2))


def traceback_wanted() -> bool:
    return os.environ.get("HYDRA_FULL_ERROR") == "1"


def hydra_line(exc: BaseException) -> str:
    """One line for an error of Hydra's composition, naming the key and the valid choices."""
    from hydra.errors import (
        ConfigCompositionException,
        MissingConfigException,
        OverrideParseException,
    )

    if isinstance(exc, MissingConfigException):  # (an OSError too, for Hydra)
        if exc.missing_cfg_file and exc.options:
            group, _, name = str(exc.missing_cfg_file).rpartition("/")
            return f"{group}={name}: no such {group}; choose one of {', '.join(exc.options)}"
        return str(exc).strip().splitlines()[0]
    if isinstance(exc, OSError):  # writing the run folder's .hydra: name that folder
        return os_line(exc, _hydra_output_dir(exc))
    if isinstance(exc, OverrideParseException):
        return _override_line(exc.override, str(exc))
    cause = exc.__cause__
    if isinstance(exc, ConfigCompositionException) and isinstance(cause, OmegaConfBaseException):
        key, parent = getattr(cause, "full_key", None), getattr(cause, "parent_node", None)
        if key and "not in struct" in str(cause):
            line = f"{key}: no such setting"
            keys = [str(k) for k in parent.keys()] if hasattr(parent, "keys") else []
            close = difflib.get_close_matches(str(cause.key), keys, n=1)
            prefix = key.rpartition(".")[0]
            return line + (
                f"; did you mean {'.'.join(filter(None, [prefix, close[0]]))}?" if close else ""
            )
    return one_line(exc)


def _override_line(override: str, message: str) -> str:
    """One line for a command-line override Hydra's grammar cannot read, with the quoting
    that makes it readable (it takes unquoted values of ASCII letters, digits and a few signs)."""
    key, _, value = override.partition("=")
    if not value.isascii() or any(c in value for c in " ()[]{}',:="):
        quoted = value.replace('"', '\\"')
        return f"{key}: Hydra reads this value only quoted; write '{key}=\"{quoted}\"'"
    return f"{override}: {message.strip().splitlines()[0]}"


def _hydra_output_dir(exc: BaseException) -> str | None:
    """The run folder of the Hydra job that raised ``exc`` (Hydra's ``run_job`` has reset its
    config by the time the error arrives here, so it is read from that frame)."""
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_code.co_name == "run_job" and "output_dir" in tb.tb_frame.f_locals:
            return str(tb.tb_frame.f_locals["output_dir"])
        tb = tb.tb_next
    return None


def in_multirun() -> bool:
    """Whether this process runs a job of a Hydra multirun (-m)."""
    from hydra.core.hydra_config import HydraConfig

    return HydraConfig.initialized() and str(HydraConfig.get().mode) == "RunMode.MULTIRUN"


def task_overrides() -> list[str]:
    """The command line's overrides of the running Hydra app (empty outside one)."""
    from hydra.core.hydra_config import HydraConfig

    return list(HydraConfig.get().overrides.task) if HydraConfig.initialized() else []


def set_threads(threads: int | None) -> None:
    """Fix torch's intra-op thread count (None: torch's default). Floating-point sums split by
    thread count, so one seed trained on two counts gives two runs; a protocol pins it."""
    if threads is not None:
        if int(threads) < 1:
            raise ValueError(f"threads: {threads}; a positive thread count, or null")
        import torch

        torch.set_num_threads(int(threads))


def rank_zero_print(text: str) -> None:
    """Print once, from the first process of a multi-process (DDP) run."""
    if rank_zero_only.rank == 0:
        print(text, flush=True)
