"""A heavy training started on a CPU says so before it starts and, after its first step, how
long the run will take here: the paper's protocol (480 px, 200 epochs, 113.7 M parameters) is
made for a GPU, and experiment=quickstart or mini are the presets a CPU finishes."""

from __future__ import annotations

import os
import time

import lightning as L
import torch

from odmv.cli import rank_zero_print

#: A CPU run at this many input pixels or more, or of a net this wide, is announced.
HEAVY_PIXELS = 256 * 256
HEAVY_WIDTH = 32


class CpuPace(L.Callback):
    """Says what is about to run when it is made (before any data is rendered or read), and the
    measured pace after the first training step."""

    def __init__(self, cfg) -> None:
        self._t0: float | None = None
        self._said = False
        rank_zero_print(
            f"on the CPU: {cfg.model.name} at {cfg.data.resolution} px for "
            f"{cfg.trainer.max_epochs} epochs: a run of this size is meant for a GPU (about a "
            f"minute a step on a 2-core CPU at 480 px). Next: {dataset_plan(cfg)}then the "
            "first training step, after which it says how long the run takes here. Ctrl-C "
            "stops it (a rerun continues a rendering); experiment=quickstart (minutes) or "
            "experiment=mini (under an hour a run) are the presets a CPU finishes"
        )

    def on_train_start(self, trainer, module) -> None:
        self._t0 = time.perf_counter()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx) -> None:
        if self._said or self._t0 is None:
            return
        self._said = True
        seconds = time.perf_counter() - self._t0
        steps = trainer.estimated_stepping_batches
        rank_zero_print(
            f"the first step took {seconds:.1f} s here: {steps} steps take about "
            f"{seconds * steps / 3600:.1f} h on this machine"
        )


def dataset_plan(cfg) -> str:
    """What the run does to its data before the first step: render a synthetic dataset (how
    many scenes and how much disk at most), or nothing."""
    sim = cfg.data.get("simulate")
    if sim is None:
        return ""
    from omegaconf import OmegaConf

    from odmv.sim.writer import SimSettings, human_size, scene_bytes_bound

    settings = SimSettings.from_dict(
        {**OmegaConf.to_container(sim, resolve=True), "out": str(cfg.data.root)}
    )
    if settings.complete():
        return ""
    need = human_size(scene_bytes_bound(settings) * settings.scenes)
    return (
        f"rendering its dataset into {cfg.data.root} ({settings.scenes} scenes at "
        f"{settings.height_px}x{settings.width_px} px, up to {need}; the simulator says how "
        "long after its first scene), "
    )


def heavy_on_cpu(cfg, accelerator: str) -> bool:
    """Whether a run is heavy for a CPU and will run on one."""
    if accelerator not in ("cpu", "auto") or torch.cuda.is_available():
        return False
    res = cfg.data.resolution
    h, w = (res, res) if isinstance(res, int) else tuple(res)
    width = cfg.model.net.get("base_width") or 0
    return h * w >= HEAVY_PIXELS or width >= HEAVY_WIDTH


class EpochLine(L.Callback):
    """One line per epoch where no progress bar shows it (a log file, ``nohup``, a scheduler):
    the epoch, its validation MAE, the time an epoch takes and about how long the rest will."""

    def __init__(self) -> None:
        self._t0: float | None = None
        self._first_epoch = 0

    def on_train_start(self, trainer, module) -> None:
        self._t0, self._first_epoch = time.perf_counter(), trainer.current_epoch

    def on_train_epoch_end(self, trainer, module) -> None:
        if self._t0 is None or trainer.sanity_checking:
            return
        done = trainer.current_epoch + 1 - self._first_epoch
        elapsed = time.perf_counter() - self._t0
        per_epoch = elapsed / max(done, 1)
        left = max(trainer.max_epochs - trainer.current_epoch - 1, 0) * per_epoch
        mae = trainer.callback_metrics.get("val/mae_mm")
        val = f"val MAE {float(mae):.4f} mm, " if mae is not None else ""
        rank_zero_print(
            f"epoch {trainer.current_epoch + 1}/{trainer.max_epochs}: {val}{per_epoch:.0f} s an "
            f"epoch, {elapsed / 60:.1f} min so far, about {left / 60:.0f} min left"
        )


def busy_cores(sample_s: float = 0.25) -> float | None:
    """How many cores other work keeps busy now: the share of non-idle time in /proc/stat over
    ``sample_s`` (this process sleeps meanwhile), times the core count. The load average would
    lag: just after ``make install`` it still counts the finished pip for a minute. Falls back
    to the 1-minute load average where /proc/stat is absent; None without either."""

    def ticks() -> tuple[int, int]:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:9]]
        return sum(v), v[3] + v[4]  # all; idle and iowait

    cores = os.cpu_count() or 1
    try:
        total0, idle0 = ticks()
        time.sleep(sample_s)
        total1, idle1 = ticks()
    except (OSError, ValueError):
        try:
            return os.getloadavg()[0]
        except OSError:
            return None
    spent = total1 - total0
    return cores * (1 - (idle1 - idle0) / spent) if spent > 0 else 0.0


def _free(cores: int, busy: float) -> int:
    """The cores other work leaves idle, rounded, at least one."""
    return max(1, min(cores, int(cores - busy + 0.5)))


def free_threads() -> tuple[int, str]:
    """The torch thread count that trains fastest now, and why: one per core that other work
    leaves idle (at least one). Beside a busy process, two threads on two cores wait on each
    other (the measurements: :func:`busy_cores_note`)."""
    cores = os.cpu_count() or 1
    busy = busy_cores()
    if busy is None:
        return cores, f"{cores} (the machine's load cannot be read)"
    threads = _free(cores, busy)
    why = (
        "an idle machine"
        if threads == cores
        else f"{busy:.1f} of {cores} cores busy with other work"
    )
    return threads, f"{threads} of {cores} cores ({why}; threads=N to choose)"


def busy_cores_note(threads: int) -> str | None:
    """A line when other work leaves fewer idle cores than torch has threads: the threads
    then wait on each other, and a step takes several times longer (measured on 2 cores beside
    one busy process: 826-964 ms a quickstart step with two threads, 397 ms with one; idle
    207 ms and 365 ms). A passive OpenMP wait changes no result and helps when busy (2-core
    EPYC, 2026-12-06: 1.18 s a step against 1.60-1.84 s beside one busy process) but costs
    6-13 % idle (562-679 ms against 522-629 ms), so it is advice, not a default. None on an
    idle enough machine or where the load cannot be read."""
    if threads <= 1:  # one thread waits on no other, and there is no fewer to advise
        return None
    busy = busy_cores()
    if busy is None:
        return None
    cores = os.cpu_count() or 1
    free = _free(cores, busy)
    if free >= threads:
        return None
    return (
        f"the machine is busy ({busy:.1f} of {cores} cores in use by other work): {threads} "
        "torch threads will wait on each other and training runs several times slower; wait "
        "for the other jobs, start it with OMP_WAIT_POLICY=PASSIVE in the environment (the "
        "same results, about 1.4x faster when busy), or train with "
        f"threads={free} (another run: results depend on the thread count)"
    )
