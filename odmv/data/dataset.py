"""Samples from a dataset folder that follows the contract (docs/dataset.md).

Reading never modifies the dataset. Images are resized to the requested resolution by area
averaging; depth and masks by picking the sample nearest each output pixel centre, so no depth
is invented between a part and the ground behind it.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from odmv.classical.geometry import triangulation_maps
from odmv.data.normalize import Normalization
from odmv.data.reference import network_input, reference_mode, reference_phase
from odmv.data.subsets import MASKS, footprint_from_depth, subset_masks
from odmv.data.views import with_availability
from odmv.io.exr import ExrError, read_exr
from odmv.io.images import NO_INTENSITY_BELOW, fringe_problem
from odmv.io.manifest import (
    DEPTH_CHANNEL,
    DEPTH_FILE,
    FOOTPRINT_FILE,
    FRINGE_CHANNEL,
    FRINGE_DIR,
    LIT_FILE,
    PROJ_COORD_FILE,
    SPLITS,
    Manifest,
    ManifestError,
    fringe_name,
)
from odmv.rig import check_views, size_hw

#: Bumped whenever a sample gains or changes an array, so stale caches are not reused.
SAMPLE_VERSION = 4


class DataError(ValueError):
    """A one-line error naming the file or config key at fault."""


@dataclass(frozen=True)
class SampleSpec:
    """What one sample holds: which views, at what size, which fringe image."""

    views: tuple[str, ...]
    height_px: int
    width_px: int
    frequency: int  # index into the manifest's periods (negative counts from the end)
    step: int
    with_stacks: bool = False  # also the full phase-shifting stacks and ground-truth phase
    with_phase: bool = False  # also (sin, cos) of the input image's ground-truth phase
    period_px: float = 0.0  # fringe period of the input image (projector px)
    n_steps: int = 1  # phase steps of its sequence
    reference: str | None = None  # the reference-plane phase as input: phase | demod
    calibration: bool = False  # also the rig's triangulation maps and the projector coordinates
    labels: bool = True  # the ground truth (depth, lit masks, projector coordinates); False:
    # the fringes alone, as a user's rig gives them (label-free adaptation never reads any)

    def key(self) -> dict:
        return asdict(self)


def check_spec(
    m: Manifest,
    views,
    resolution,
    frequency: int | None,
    step: int | None,
    with_stacks: bool = False,
    with_phase: bool = False,
    reference=None,
    calibration: bool = False,
    labels: bool = True,
) -> SampleSpec:
    """Resolve and check sample settings against a manifest (one-line DataError on a problem)."""
    try:
        views = check_views(list(views))
    except ValueError as e:
        raise DataError(f"views: {e}") from None
    missing = [v for v in views if v not in m.views]
    if missing:
        raise DataError(f"views: {missing} not in dataset {m.root} (it has {list(m.views)})")
    h, w = size_hw(resolution, "data.resolution")
    if h % 16 or w % 16 or h <= 0 or w <= 0:
        raise DataError(f"data.resolution: {h}x{w} must be positive multiples of 16")
    f = m.fringe.train_frequency if frequency is None else frequency
    s = m.fringe.train_step if step is None else step
    try:
        f = m.fringe.resolve_frequency(f)
    except ManifestError as e:
        raise DataError(f"data.fringe_frequency: {e}") from None
    if not 0 <= s < m.fringe.steps:
        raise DataError(f"data.fringe_step: {s} out of range for {m.fringe.steps} steps")
    if m.images == "training" and (f, s) != (
        m.fringe.resolve_frequency(m.fringe.train_frequency),
        m.fringe.train_step,
    ):
        raise DataError(f"data.fringe_frequency/step: {m.root} holds only the training image")
    try:
        reference = reference_mode(reference)
    except ValueError as e:
        raise DataError(str(e)) from None
    if with_stacks and m.images != "full":
        raise DataError(f"data.with_stacks: {m.root} holds no full sequences (images=training)")
    if not labels and (with_stacks or with_phase):
        raise DataError("data.labels: false reads no ground truth, so no stacks or phase targets")
    if calibration and m.rig is None:
        raise DataError(
            f"head=phase: {m.root} has no rig calibration, so phase cannot become depth; "
            "use head=depth"
        )
    return SampleSpec(
        views,
        h,
        w,
        f,
        s,
        with_stacks,
        with_phase,
        m.fringe.periods_px[f],
        m.fringe.steps,
        reference,
        calibration,
        labels,
    )


def matching_fringe(m: Manifest, input_spec: dict, views, where) -> tuple[int, int]:
    """The (frequency, step) of dataset ``m`` whose image is the one a net was trained on
    (``input_spec``: a checkpoint's, its fringe period in projector px, its phase step of
    how many): the manifest's network image, or with full sequences the image of that period
    at the same phase shift; refused, naming ``where``, when the dataset holds none or lacks
    one of the net's ``views``. An import that does not know its period is taken as it is."""
    lost = [v for v in views if v not in m.views]
    if lost:
        raise DataError(
            f"{where}: no view {', '.join(lost)} in its dataset (it has {', '.join(m.views)}); "
            f"the checkpoint takes {', '.join(views)}"
        )
    frequency = m.fringe.resolve_frequency(m.fringe.train_frequency)
    period, step = input_spec.get("period_px"), input_spec.get("step")
    if period is None or m.extra.get("fringe_period_known") is False:
        return frequency, m.fringe.train_step  # nothing to compare (an import)
    periods = list(m.fringe.periods_px)
    shift = step * m.fringe.steps / (input_spec.get("n_steps") or m.fringe.steps)  # in its steps
    same = abs(shift - round(shift)) < 1e-6
    if abs(periods[frequency] - period) < 1e-6 and same and m.fringe.train_step == round(shift):
        return frequency, round(shift)
    if m.images == "full" and same:
        for f, p in enumerate(periods):
            if abs(p - period) < 1e-6:
                return f, round(shift) % m.fringe.steps
    held = ", ".join(f"{p:g}" for p in periods) if m.images == "full" else f"{periods[frequency]:g}"
    raise DataError(
        f"{where}: its dataset holds the {held} px fringe(s) (period in projector px; "
        f"{m.fringe.steps} steps{'' if m.images == 'full' else ', one image'}); the checkpoint "
        f"was trained on the {period:g} px fringe at step {step} of {input_spec.get('n_steps')}"
        ": capture or render that fringe (a dataset with full sequences, images=full, holds "
        "every fringe it was made with)"
    )


def split_scenes(m: Manifest, fractions: dict | None, seed: int) -> dict[str, list[str]]:
    """Scene ids per split: the manifest's labels when every scene has one, else a seeded
    permutation cut by ``fractions`` (train/val/test)."""
    ids = [s["id"] for s in m.scenes]
    labels = [s.get("split") for s in m.scenes]
    if all(lab in SPLITS for lab in labels):
        return {k: [i for i, lab in zip(ids, labels, strict=True) if lab == k] for k in SPLITS}
    fractions = fractions or {"train": 0.8, "val": 0.1, "test": 0.1}
    w = np.array([float(fractions.get(k, 0)) for k in SPLITS])
    if (w < 0).any() or w.sum() <= 0:
        raise DataError(f"data.split_fractions: {fractions} must be non-negative, not all zero")
    perm = [ids[i] for i in np.random.default_rng(seed).permutation(len(ids))]
    n_val = int(round(w[1] / w.sum() * len(ids)))
    n_test = int(round(w[2] / w.sum() * len(ids)))
    n_train = len(ids) - n_val - n_test
    return {
        "train": perm[:n_train],
        "val": perm[n_train : n_train + n_val],
        "test": perm[n_train + n_val :],
    }


def hold_out_val(splits: dict[str, list[str]], share: float, seed: int) -> int:
    """Move a seeded ``share`` of the training scenes (at least one) into an empty val split;
    returns how many moved. For sources labelled train and test only."""
    if not 0 < share < 1:
        raise DataError(f"data.val_from_train: {share} must lie between 0 and 1")
    train = splits["train"]
    n = max(1, int(round(share * len(train))))
    if n >= len(train):
        raise DataError(
            f"data.val_from_train: {len(train)} training scene(s) cannot spare {n} for val"
        )
    picked = set(np.random.default_rng(seed).permutation(len(train))[:n].tolist())
    splits["val"] = [sid for i, sid in enumerate(train) if i in picked]
    splits["train"] = [sid for i, sid in enumerate(train) if i not in picked]
    return n


def _resize(a: np.ndarray, h: int, w: int, mode: str) -> np.ndarray:
    if a.shape[-2:] == (h, w):
        return a
    t = torch.from_numpy(np.ascontiguousarray(a))[None]
    return F.interpolate(t, size=(h, w), mode=mode)[0].numpy()


def _read(path: Path, channels: list[str]) -> dict[str, np.ndarray]:
    try:
        return read_exr(path, channels)
    except ExrError as e:
        raise DataError(str(e)) from None


def _full_depth(m: Manifest, sid: str) -> np.ndarray:
    """A scene's depth map (mm) at the dataset's size, NaN where it has no ground truth (only
    where the manifest declares ``invalid_depth``, as imported datasets do); refuses a wrong
    shape, infinite values or NaN in a dataset that promises none."""
    path = m.scene_dir(sid) / DEPTH_FILE
    depth = _read(path, [DEPTH_CHANNEL])[DEPTH_CHANNEL].astype(np.float32, copy=False)
    if depth.shape != (m.height_px, m.width_px):
        raise DataError(
            f"{path}: shape {depth.shape} differs from the manifest's {(m.height_px, m.width_px)}"
        )
    bad = np.isinf(depth) if m.extra.get("invalid_depth") else ~np.isfinite(depth)
    if bad.any() or np.isnan(depth).all():
        raise DataError(f"{path}: {int(bad.sum())} non-finite depth values")
    return depth


def load_depth(m: Manifest, sid: str, spec: SampleSpec) -> np.ndarray:
    """A scene's depth (mm) at ``spec``'s size, (1,H,W), resampled as :func:`load_scene` does."""
    return _resize(_full_depth(m, sid)[None], spec.height_px, spec.width_px, "nearest-exact")


def load_scene(m: Manifest, sid: str, spec: SampleSpec) -> dict[str, np.ndarray]:
    """Raw arrays of one scene at ``spec``'s size: fringes (S,H,W) linear intensity and, unless
    ``spec.labels`` is false (then nothing else is read), depth_mm (1,H,W), lit (S,H,W) bool,
    the subsets shadowed, unlit, first_unlit and first_shadowed (1,H,W) bool over every
    projector of the dataset; with stacks also
    fringe_stack (S,K,H,W); with stacks or calibration projector_coord (S,H,W, NaN where
    unlit); with phase (or calibration) also phase_target (2S,H,W: sin, cos of each view's
    input-image phase, 0 where unlit).
    Raises DataError naming a bad file."""
    d = m.scene_dir(sid)
    shape = (m.height_px, m.width_px)
    fd = d / FRINGE_DIR
    paths = [fd / fringe_name(v, spec.frequency, spec.step) for v in spec.views]
    fringes = np.stack([_fringe(p, shape) for p in paths])
    dark = m.dark_views()
    for path, view, image in zip(paths, spec.views, fringes, strict=True):
        # the net's image must hold a fringe: training on a black one teaches nothing
        problem = None if view in dark else fringe_problem(path, image)
        if problem:
            raise DataError(f"{problem}; python -m odmv.validate {m.root} checks every image")
    h, w = spec.height_px, spec.width_px
    if not spec.labels:
        return {"fringes": _resize(fringes, h, w, "area")}
    depth = _full_depth(m, sid)
    # every projector's lit mask: the metric subsets never depend on the model's views
    lit_all = _read(d / LIT_FILE, list(m.views))
    lit_every = np.stack([lit_all[v] for v in m.views]) > 0.5
    if lit_every.shape[1:] != shape:
        raise DataError(
            f"{d / LIT_FILE}: shape {lit_every.shape[1:]} differs from the manifest's {shape}"
        )
    if (d / FOOTPRINT_FILE).is_file():
        foot = _read(d / FOOTPRINT_FILE, list(m.views))
        footprint = np.stack([foot[v] for v in m.views]) > 0.5
    else:
        footprint = footprint_from_depth(m.rig, depth, m.views)
    subsets = subset_masks(lit_every, footprint)
    lit = lit_every[[m.views.index(v) for v in spec.views]].astype(np.float32)
    out = {
        "fringes": _resize(fringes, h, w, "area"),
        "depth_mm": _resize(depth[None], h, w, "nearest-exact"),
        "lit": _resize(lit, h, w, "nearest-exact") > 0.5,
    }
    for name, mask in subsets.items():
        out[name] = _resize(mask.astype(np.float32), h, w, "nearest-exact") > 0.5
    if spec.with_stacks or spec.with_phase or spec.calibration:
        coord = _read(d / PROJ_COORD_FILE, list(spec.views))
        coord = _resize(np.stack([coord[v] for v in spec.views]), h, w, "nearest-exact")
    if spec.calibration:
        out["projector_coord"] = coord.astype(np.float32)
    if spec.with_phase or spec.calibration:
        # the image is A + B cos(phase): phase = 2 pi u / P + 2 pi n / N
        phase = 2 * np.pi * (coord / spec.period_px + spec.step / spec.n_steps)
        sc = np.stack([np.sin(phase), np.cos(phase)], 1).reshape(-1, h, w)
        out["phase_target"] = np.nan_to_num(sc, nan=0.0).astype(np.float32)
    if spec.with_stacks:
        out["fringe_stack"] = load_stack(m, sid, spec.views, h, w)
        out["projector_coord"] = coord
    return out


def _fringe(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """One fringe image (linear intensity), refused with a one-line DataError naming the file
    where it is not of the manifest's ``shape`` or not what a camera records."""
    a = _read(path, [FRINGE_CHANNEL])[FRINGE_CHANNEL]
    if a.shape != shape:
        raise DataError(f"{path}: shape {a.shape} differs from the manifest's {shape}")
    if not np.isfinite(a).all():  # would train to NaN on every metric
        raise DataError(f"{path}: {int((~np.isfinite(a)).sum())} non-finite intensity values")
    if a.min() < NO_INTENSITY_BELOW:  # what a corrupted file decodes to
        raise DataError(
            f"{path}: intensities down to {a.min():.3g}, which no camera records (a "
            "corrupted file?); render or convert the scene again"
        )
    return a.astype(np.float32, copy=False)


def load_stack(m: Manifest, sid: str, views, h: int, w: int) -> np.ndarray:
    """Every phase-shifted image of ``views`` of a scene of a dataset with the full sequences,
    at h x w: (S, F x N, H, W) linear intensity, frequencies in the manifest's order, steps
    within each. Reads no labels."""
    fd, shape = m.scene_dir(sid) / FRINGE_DIR, (m.height_px, m.width_px)
    n_f, n_s = len(m.fringe.periods_px), m.fringe.steps
    names = [[fringe_name(v, f, s) for f in range(n_f) for s in range(n_s)] for v in views]
    stacks = [np.stack([_fringe(fd / n, shape) for n in ns]) for ns in names]
    return np.stack([_resize(x, h, w, "area") for x in stacks])


def fingerprint(m: Manifest, ids: list[str], spec: SampleSpec) -> str:
    """Changes whenever the manifest, the sample settings or any file read changes."""
    h = hashlib.sha1(f"odmv-sample-v{SAMPLE_VERSION}".encode())
    h.update(json.dumps(m.to_json(), sort_keys=True).encode())
    h.update(json.dumps(spec.key(), sort_keys=True).encode())
    for sid in ids:
        d = m.scene_dir(sid)
        files = [d / FRINGE_DIR / fringe_name(v, spec.frequency, spec.step) for v in spec.views]
        if spec.labels:
            coord = spec.with_phase or spec.calibration
            files += [d / DEPTH_FILE, d / LIT_FILE] + ([d / PROJ_COORD_FILE] if coord else [])
            files += [d / FOOTPRINT_FILE] if (d / FOOTPRINT_FILE).is_file() else []
        for p in files:
            try:
                st = p.stat()
            except FileNotFoundError:
                raise DataError(f"{p}: no such file") from None
            h.update(f"{p.relative_to(m.root)}:{st.st_size}:{st.st_mtime_ns}".encode())
    return h.hexdigest()[:16]


def _rig_maps(make, m: Manifest, spec: SampleSpec) -> torch.Tensor:
    """Per-view maps of the rig for the input image (the reference phase, the triangulation)."""
    size = (spec.height_px, spec.width_px)
    return torch.from_numpy(make(m.rig, spec.views, *size, spec.period_px, spec.step, spec.n_steps))


class FringeDataset(torch.utils.data.Dataset):
    """One scene per item: a dict of tensors (see :meth:`__getitem__`).

    ``cache`` is an optional :class:`odmv.data.cache.ArrayCache` holding the same arrays
    decoded; items from it are identical to items read from the EXR files.
    """

    def __init__(
        self,
        m: Manifest,
        ids: list[str],
        spec: SampleSpec,
        norm: Normalization,
        cache=None,
        availability: bool = False,
    ):
        self.manifest, self.ids, self.spec, self.norm, self.cache = m, list(ids), spec, norm, cache
        self.availability = availability  # inputs carry each view's availability (odmv.data.views)
        self.families = {s["id"]: str(s.get("family", "")) for s in m.scenes}
        self.reference = _rig_maps(reference_phase, m, spec) if spec.reference else None
        self.calibration = _rig_maps(triangulation_maps, m, spec) if spec.calibration else None

    def __len__(self) -> int:
        return len(self.ids)

    def __getitem__(self, i: int) -> dict:
        """fringes (S,H,W) in [-1,1]; depth (1,H,W) network units; depth_mm (1,H,W; NaN without
        labels); lit (S,H,W)
        and valid (1,H,W) as 0/1 floats; the metric subsets shadowed, unlit, first_unlit and
        first_shadowed (1,H,W, 0/1, see odmv.data.subsets); scene_id and family; with stacks also
        fringe_stack (S,K,H,W) in [-1,1]; with stacks or calibration projector_coord (S,H,W) in
        projector px (NaN where unlit); with calibration the rig's triangulation maps
        (S,6,H,W, odmv.classical.geometry) as ``calibration``."""
        if self.cache is not None and not self.spec.with_stacks:
            raw = self.cache.get(i)
        else:
            raw = load_scene(self.manifest, self.ids[i], self.spec)
        if not self.spec.labels:  # no truth: NaN depth, nothing lit, every subset empty
            shape = raw["fringes"].shape[1:]
            raw = raw | {
                "depth_mm": np.full((1, *shape), np.nan, np.float32),
                "lit": np.zeros(raw["fringes"].shape, np.float32),
                **{k: np.zeros((1, *shape), np.float32) for k in MASKS},
            }
        depth_mm = torch.from_numpy(np.array(raw["depth_mm"], np.float32))
        sample = {
            "fringes": self.norm.fringes(torch.from_numpy(np.array(raw["fringes"], np.float32))),
            "depth_mm": depth_mm,
            "depth": self.norm.depth(depth_mm),
            "lit": torch.from_numpy(np.array(raw["lit"], np.float32)),
            "valid": torch.isfinite(depth_mm).float(),
            **{k: torch.from_numpy(np.array(raw[k], np.float32)) for k in MASKS},
            "scene_id": self.ids[i],
            "family": self.families.get(self.ids[i], ""),
        }
        if self.reference is not None:
            sample["inputs"] = network_input(sample["fringes"], self.reference, self.spec.reference)
        if self.availability:
            sample["available"] = torch.ones(len(self.spec.views))
            base = sample.get("inputs", sample["fringes"])
            sample["inputs"] = with_availability(base, sample["available"])
        labelled = self.spec.labels
        if labelled and (self.spec.with_phase or self.spec.calibration):
            sample["phase_target"] = torch.from_numpy(np.array(raw["phase_target"], np.float32))
        if self.spec.with_stacks:
            sample["fringe_stack"] = self.norm.fringes(torch.from_numpy(raw["fringe_stack"]))
        if labelled and (self.spec.with_stacks or self.spec.calibration):
            sample["projector_coord"] = torch.from_numpy(np.array(raw["projector_coord"]))
        if self.calibration is not None:
            sample["calibration"] = self.calibration
        return sample
