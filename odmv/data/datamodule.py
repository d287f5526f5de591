"""LightningDataModule over a dataset folder, rendering the synthetic default when it is missing."""

from __future__ import annotations

import json
import os
from dataclasses import replace
from pathlib import Path

import lightning as L
import numpy as np
import torch
import torch.distributed as dist
from lightning.pytorch.overrides.distributed import UnrepeatedDistributedSampler
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn
from torch.utils.data import ConcatDataset, DistributedSampler

from odmv.cli import rank_zero_print
from odmv.data.augment import AUGMENTS, QuarterTurns
from odmv.data.cache import ArrayCache
from odmv.data.dataset import (
    DataError,
    FringeDataset,
    SampleSpec,
    check_spec,
    fingerprint,
    hold_out_val,
    load_depth,
    load_scene,
    split_scenes,
)
from odmv.data.normalize import Normalization
from odmv.data.views import ViewDropout
from odmv.io.manifest import MANIFEST, SPLITS, Manifest, ManifestError, load_manifest
from odmv.rig import VIEW_NAMES

#: The splits each Lightning stage reads (evaluation never decodes the training split).
_STAGE_SPLITS = {
    "fit": ("train", "val"),
    "validate": ("val",),
    "test": ("test",),
    "predict": ("test",),
}


class FPPDataModule(L.LightningDataModule):
    """Train/val/test loaders of fringe samples (see :class:`FringeDataset`).

    ``simulate``: settings for :class:`odmv.sim.writer.SimSettings` (minus ``out``) used to render
    the dataset into ``root`` when ``root`` holds no manifest; None means the data must exist.
    ``reference``: add the reference-plane phase to the net's input (odmv.data.reference).
    ``render``: False for a dataset the user names (``data=exr``): it is read, never written,
    even when a preset has filled in ``simulate``.
    ``train_steps``: beyond the paper, more training samples from the same scenes: the phase
    steps of the input frequency that the train split draws from ("all", or a list of step
    indices; needs a dataset with full sequences). Each step is one more sample per scene, with
    its own reference phase; validation and test keep ``fringe_step``, so the protocol's
    metrics do not change. None: the paper's one image per scene.
    ``augment``: beyond the paper, ``"rot90"`` turns each training sample by a random number of
    quarter turns, the rig's symmetry (:mod:`odmv.data.augment`; needs square images and a
    dataset of all four views, which the train split then loads). None: no augmentation.
    ``view_dropout``: beyond the paper, the probability with which each view of a training
    sample is dropped (at least one kept); every sample's input then carries each view's
    availability (:mod:`odmv.data.views`). None: every view always, and no availability input.
    ``randomize``: the name of the domain-randomization profile the synthetic dataset was asked
    with (conf/randomize/); the profile itself reaches the simulator through ``simulate``.
    ``calibration``: beyond the paper, for ``head=phase``: every sample carries the rig's
    triangulation maps (odmv.classical.geometry), each view's projector coordinates and phase
    targets
    (needs a dataset with a rig). None: none of them.
    ``labels``: False reads the fringes alone, never a scene's depth, lit masks or projector
    coordinates (their files may be absent): a user's rig for label-free adaptation
    (odmv.training.consistency); the samples' depth is NaN and every metric subset empty.
    ``replay``: the settings of a second data module whose labelled training scenes come with
    every training batch, as ``{"own": batch, "replay": batch}`` (one epoch: this dataset's
    batches); None: none.
    """

    def __init__(
        self,
        root: str,
        views=("right", "down", "left", "up"),
        resolution: int | list[int] = 480,
        batch_size: int = 2,
        eval_batch_size: int | None = None,
        num_workers: int = 0,
        fringe_frequency: int | None = None,
        fringe_step: int | None = None,
        with_stacks: bool = False,
        with_phase: bool = False,
        split_seed: int = 0,
        split_fractions: dict | None = None,
        val_from_train: float | None = None,
        cache: bool = True,
        cache_dir: str | None = None,
        depth_half_range_mm: float = 10.0,
        depth_target: str = "depth",
        intensity_max: float | None = None,
        simulate: dict | None = None,
        render: bool = True,
        reference: bool | str = False,
        train_steps: str | list[int] | None = None,
        augment: str | None = None,
        randomize: str | None = None,
        view_dropout: float | None = None,
        calibration: bool | None = None,
        labels: bool = True,
        replay: dict | None = None,
        progress: bool = True,
    ):
        super().__init__()
        if root is None:
            raise DataError("data.root: no dataset folder given (data=exr root=PATH)")
        self.root = Path(root)
        self.views = tuple(views)
        self.resolution = resolution
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size or batch_size
        self.num_workers = num_workers
        self.fringe_frequency, self.fringe_step = fringe_frequency, fringe_step
        self.with_stacks, self.with_phase = with_stacks, with_phase
        self.split_seed, self.split_fractions = split_seed, split_fractions
        self.val_from_train = val_from_train
        self.cache = cache
        self.cache_dir = Path(cache_dir) if cache_dir else self.root.parent / ".odmv-cache"
        self.depth_half_range_mm, self.intensity_max = depth_half_range_mm, intensity_max
        self.depth_target = depth_target
        self.simulate = simulate if render else None
        self.reference = reference
        if augment not in AUGMENTS:
            raise DataError(f"data.augment: {augment!r} unknown; choose null or rot90")
        if augment and calibration:
            # a turned sample would need its calibration maps turned and re-assigned too
            raise DataError("data.augment: rot90 is not supported with head=phase; use null")
        self.train_steps, self.augment = train_steps, augment
        self.randomize = randomize
        self.view_dropout = view_dropout
        self.calibration = bool(calibration)
        self.labels = bool(labels)
        # another dataset's labelled training scenes, batched beside this one's (adaptation's
        # replay of the twin a net was trained on)
        self.replay = None
        if replay:
            self.replay = FPPDataModule(**(replay | {"labels": True, "replay": None}))
        self.progress = progress
        self.manifest: Manifest | None = None
        self.spec: SampleSpec | None = None
        self.norm: Normalization | None = None
        self.splits: dict[str, list[str]] = {}
        self.datasets: dict[str, torch.utils.data.Dataset] = {}

    # ------------------------------------------------------------------ preparation
    def prepare_data(self) -> None:
        """Render the synthetic dataset, or finish an interrupted render (rank zero only)."""
        if self.replay is not None:
            self.replay.prepare_data()
        if self.simulate is None:
            if (self.root / MANIFEST).is_file():
                return
            raise DataError(
                f"{self.root / MANIFEST}: no dataset here (set data.root to a dataset "
                "folder, or use data=synthetic to render one)"
            )
        from odmv.sim.writer import SimSettings, simulate  # only needed when rendering

        settings = SimSettings.from_dict({**self.simulate, "out": str(self.root)})
        if not settings.complete():
            print(f"rendering the synthetic dataset into {self.root} (once; later runs reuse it)")
            simulate(settings, workers=self.simulate.get("workers"), progress=self.progress)

    def setup(self, stage: str | None = None) -> None:
        """Read the manifest, then check (and cache) the splits the stage uses: fit decodes
        train and val, validate val, test and predict only test; None decodes all three."""
        if self.manifest is None:
            self._read_manifest()
        if self.replay is not None and stage in ("fit", None):
            self.replay.setup("fit")
        for name in _STAGE_SPLITS.get(stage, ("train", "val", "test")):
            if name in self.datasets:
                continue
            ids = self.splits[name]
            specs = self._train_specs() if name == "train" and self.train_steps else [self.spec]
            turned = name == "train" and self.augment is not None
            if turned:  # every view is loaded: a turn maps each view onto another
                specs = [replace(spec, views=self._all_views()) for spec in specs]
            parts = [
                FringeDataset(
                    self.manifest,
                    ids,
                    spec,
                    self.norm,
                    self._checked_cache(name, ids, spec),
                    availability=self.view_dropout is not None,
                )
                for spec in specs
            ]
            if turned:
                parts = [QuarterTurns(part, self.spec.views) for part in parts]
            if name == "train" and self.view_dropout:
                parts = [ViewDropout(part, self.view_dropout) for part in parts]
            self.datasets[name] = parts[0] if len(parts) == 1 else ConcatDataset(parts)

    def _read_manifest(self) -> None:
        try:
            m = load_manifest(self.root)
        except ManifestError as e:
            raise DataError(str(e)) from None
        self.spec = check_spec(
            m,
            self.views,
            self.resolution,
            self.fringe_frequency,
            self.fringe_step,
            self.with_stacks,
            self.with_phase,
            self.reference,
            self.calibration,
            self.labels,
        )
        if self.spec.height_px > m.height_px or self.spec.width_px > m.width_px:
            rank_zero_print(
                f"data.resolution {self.spec.height_px}x{self.spec.width_px}: above the "
                f"dataset's {m.height_px}x{m.width_px} px, so images and ground truth are "
                "upsampled (the net learns interpolated depth); render the dataset at that size"
            )
        sat = m.extra.get("simulation", {}).get("render", {}).get("saturation", 1.0)
        intensity_max = self.intensity_max if self.intensity_max is not None else sat
        if self.reference and m.rig is None:
            raise DataError(
                f"reference: {m.root} has no rig calibration, so the reference-plane phase is "
                "unknown; use reference=false"
            )
        if "depth_range_mm" in m.extra:  # an import: its own depth (or height) range
            lo, hi = m.extra["depth_range_mm"]
            self.norm = Normalization.for_depth_range(
                lo, hi, intensity_max, self.depth_target, stored=m.quantity
            )
        else:
            self.norm = Normalization.for_working_distance(
                m.rig.camera.working_distance_mm,
                self.depth_half_range_mm,
                intensity_max,
                self.depth_target,
            )
        self.splits = split_scenes(m, self.split_fractions, self.split_seed)
        if self.val_from_train and not self.splits["val"]:
            n = hold_out_val(self.splits, self.val_from_train, self.split_seed)
            print(
                f"data.val_from_train={self.val_from_train}: {n} of the "
                f"{n + len(self.splits['train'])} training scenes are the val split "
                f"(seed {self.split_seed})",
                flush=True,
            )
        self.manifest = m

    def check_splits(self, test: bool) -> None:
        """Refuse, before the first epoch, a split the run needs that the dataset leaves
        empty: training needs train scenes, and a run that tests needs test scenes. (A
        synthetic dataset not rendered yet is checked when it is read.)"""
        if self.manifest is None:
            if not (self.root / MANIFEST).is_file():
                return
            self._read_manifest()
        for name in ("train", "test") if test else ("train",):
            if not self.splits[name]:
                sizes = ", ".join(f"{k} {len(v)}" for k, v in self.splits.items())
                labelled = all(sc.get("split") in SPLITS for sc in self.manifest.scenes)
                fix = (
                    f"its manifest labels no scene {name}"
                    if labelled
                    else "render more scenes or change data.split_fractions"
                )
                raise DataError(
                    f"{self.root}: no {name} scenes ({sizes}); {fix}"
                    + (", or train with test=false" if name == "test" else "")
                )

    def mean_depth_mm(self, split: str = "train") -> float | None:
        """Mean ground-truth depth (mm) of a split at the network's size, from the depth maps
        alone: the constant predictor's value, without decoding the split's fringes (None for
        a split without valid pixels, e.g. a dataset labelled test only)."""
        if self.manifest is None:
            self._read_manifest()
        total, count = 0.0, 0
        for sid in self.splits[split]:
            depth = load_depth(self.manifest, sid, self.spec)
            total += float(np.nansum(depth, dtype=np.float64))
            count += int(np.isfinite(depth).sum())
        return total / count if count else None

    def _train_specs(self) -> list[SampleSpec]:
        """One sample spec per phase step of ``train_steps`` (checked like ``fringe_step``)."""
        m = self.manifest
        steps = range(m.fringe.steps) if self.train_steps == "all" else self.train_steps
        if isinstance(steps, str) or not len(steps):
            raise DataError(
                f"data.train_steps: {self.train_steps!r} is not 'all' or a list of steps"
            )
        if m.images != "full":
            raise DataError(
                f"data.train_steps: {m.root} holds only the training image (render it with "
                "images=full)"
            )
        return [replace(self.spec, step=self._step(s)) for s in steps]

    def _all_views(self) -> tuple[str, ...]:
        m = self.manifest
        if not set(VIEW_NAMES) <= set(m.views):
            raise DataError(
                f"data.augment: {m.root} holds the views {list(m.views)}; a quarter turn "
                f"maps each view onto another, so it needs all of {list(VIEW_NAMES)}"
            )
        if self.spec.height_px != self.spec.width_px:
            raise DataError(
                f"data.augment: a quarter turn needs square images, not "
                f"data.resolution {self.spec.height_px}x{self.spec.width_px}"
            )
        return VIEW_NAMES

    def _step(self, s) -> int:
        n = self.manifest.fringe.steps
        if not isinstance(s, int) or not 0 <= s < n:
            raise DataError(f"data.train_steps: {s!r} out of range for {n} steps")
        return s

    def _checked_cache(self, split: str, ids: list[str], spec: SampleSpec) -> ArrayCache | None:
        """Decode every sample of a split once, so bad files fail here, not mid-epoch; with
        the cache on, the decoded arrays are kept for the epochs to come."""
        if not ids:
            return None
        key = fingerprint(self.manifest, ids, spec) if self.cache else None
        folder = self.cache_dir / f"{self.root.name}-{split}-{key}" if key else None
        if folder is not None and ArrayCache.complete(folder):
            return ArrayCache(folder)

        def load(sid):
            return load_scene(self.manifest, sid, spec)

        label = split if spec == self.spec else f"{split} (step {spec.step})"
        columns = (TextColumn(f"checking {label}"), BarColumn(), MofNCompleteColumn())
        with Progress(*columns, disable=not self.progress, transient=True) as bar:
            task = bar.add_task(split, total=len(ids))
            if folder is None:
                for sid in ids:
                    load(sid)
                    bar.advance(task)
                return None
            return ArrayCache.build(folder, ids, spec, load, lambda: bar.advance(task))

    # ------------------------------------------------------------------ loaders
    def _loader(self, split: str, shuffle: bool) -> torch.utils.data.DataLoader:
        ds = self.datasets.get(split)
        if ds is None or len(ds) == 0:
            labelled = all(sc.get("split") in SPLITS for sc in self.manifest.scenes)
            if labelled and split == "val":
                fix = "set data.val_from_train=0.1 to hold out a share of the training scenes"
            elif labelled:
                fix = "its scenes are labelled (data.split_fractions does not apply): add scenes"
            else:
                fix = "add scenes or change data.split_fractions"
            raise DataError(f"data: the {split} split of {self.root} is empty; {fix}")
        sampler = None
        if split != "train" and dist.is_available() and dist.is_initialized():
            # DDP: each rank gets its share of the scenes, none twice (Lightning's default
            # sampler pads with repeats, which the metrics would count twice). A split smaller
            # than the number of ranks is evaluated whole by every rank: the metrics' sums
            # then grow alike, so every mean is the same as from one process.
            if len(ds) >= dist.get_world_size():
                sampler = UnrepeatedDistributedSampler(ds, shuffle=False)
            else:
                sampler = DistributedSampler(ds, num_replicas=1, rank=0, shuffle=False)
        return torch.utils.data.DataLoader(
            ds,
            batch_size=self.batch_size if split == "train" else self.eval_batch_size,
            shuffle=shuffle,
            sampler=sampler,
            num_workers=self.num_workers,
            persistent_workers=self.num_workers > 0,
            drop_last=False,
        )

    def train_dataloader(self):
        own = self._loader("train", shuffle=True)
        if self.replay is None:
            return own
        from lightning.pytorch.utilities import CombinedLoader

        return CombinedLoader({"own": own, "replay": self.replay.train_dataloader()}, "min_size")

    def val_dataloader(self):
        return self._loader("val", shuffle=False)

    def test_dataloader(self):
        return self._loader("test", shuffle=False)

    # ------------------------------------------------------------------ bookkeeping
    def save_split(self, path: str | os.PathLike) -> Path:
        """Write the scene ids of each split used (kept with the run's outputs)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"root": str(self.root.resolve()), **self.splits}, indent=1))
        return path
