"""Render many scenes into a dataset folder that follows the contract (docs/dataset.md).

Each scene is drawn from its own seed sequence ``[seed, index]``, rendered into a hidden
temporary folder and renamed into place when complete, so an interrupted run never leaves half a
scene, a rerun skips finished scenes, and the result does not depend on the number of workers.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import OpenEXR
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from odmv.io.exr import write_exr
from odmv.io.guard import refuse_inside
from odmv.io.manifest import (
    DEPTH_CHANNEL,
    DEPTH_FILE,
    FOOTPRINT_FILE,
    FRINGE_CHANNEL,
    FRINGE_DIR,
    LIT_FILE,
    MANIFEST,
    PROJ_COORD_FILE,
    SCENE_SPEC_FILE,
    SPLITS,
    FringeSpec,
    Manifest,
    load_manifest,
)
from odmv.io.processes import die_with_parent
from odmv.rig import Rig, check_views, size_hw, whole_number
from odmv.sim.pose import PoseSettings
from odmv.sim.render import RenderConfig, Rendered, render_scene
from odmv.sim.scenes import Scene, build_scene, choose_family, draw_spec, mesh_files_in
from odmv.sim.shifts import NOMINAL, NOMINAL_SHIFT, Shift, apply

PARTIAL_PREFIX = ".partial-"


class SimulationError(ValueError):
    """A one-line error about simulation settings or the output folder."""


@dataclass
class SimSettings:
    """Everything that determines a dataset's content (stored in the manifest)."""

    out: Path
    scenes: int = 252  # the paper's dataset size, as conf/simulate.yaml
    family: str = "mix"
    height_px: int = 480
    width_px: int = 480
    seed: int = 0
    images: str = "full"
    views: tuple[str, ...] = ("right", "down", "left", "up")
    mix: dict = field(default_factory=lambda: {"primitives": 0.35, "pcb": 0.4, "freeform": 0.25})
    mesh_dir: str | None = None
    splits: dict | None = field(default_factory=lambda: {"train": 0.8, "val": 0.1, "test": 0.1})
    fringe: FringeSpec = field(default_factory=FringeSpec)
    render: RenderConfig = field(default_factory=RenderConfig)
    rig: Rig = field(default_factory=Rig)  # the nominal rig: the manifest's calibration
    shift: Shift = NOMINAL_SHIFT  # what renders the images differs from it (odmv.sim.shifts)
    # domain randomization: {shift name: [low, high]}; each training scene draws every listed
    # shift's strength from its range (validation and test scenes stay as ``shift`` says)
    randomize: dict | None = None
    compression: str = "zstd"
    fringe_dtype: str = "float32"
    pose: PoseSettings = field(default_factory=PoseSettings)  # fixed, or scenes that move
    # the prior probe (odmv.study.prior): every scene moved {offset_mm, tilt_deg} after its pose
    move: dict | None = None
    subset: tuple[int, ...] | None = None  # the scene indices rendered (None: all of them)

    @classmethod
    def from_dict(cls, c: dict) -> SimSettings:
        """Settings from a plain dict shaped like conf/simulate.yaml; absent keys keep defaults.
        Keys that steer a run rather than its content (workers, validate, progress) are ignored."""
        kw: dict = {"out": Path(c["out"])}
        res = c.get("resolution")
        if res is not None:
            kw["height_px"], kw["width_px"] = size_hw(res)
        lows = {"scenes": (1, "render at least one scene"), "seed": (0, "0 or more")}
        for key, (low, what) in lows.items():
            if key in c:
                kw[key] = whole_number(c[key], key, low, what)
        for key in ("family", "images", "mesh_dir", "splits", "compression", "fringe_dtype"):
            if key in c:
                kw[key] = c[key]
        if "views" in c:
            kw["views"] = tuple(c["views"])
        if "mix" in c:
            kw["mix"] = dict(c["mix"])
        if "fringe" in c:
            fr = {**asdict(FringeSpec()), **c["fringe"]}
            fr["periods_px"] = tuple(float(p) for p in fr["periods_px"])
            kw["fringe"] = FringeSpec(**fr)
        if "render" in c:
            kw["render"] = RenderConfig(**c["render"])
        if "rig" in c:
            kw["rig"] = Rig.from_dict(c["rig"])
        if c.get("shift"):
            kw["shift"] = Shift(**c["shift"])
        if c.get("randomize"):
            kw["randomize"] = {k: [float(lo), float(hi)] for k, (lo, hi) in c["randomize"].items()}
        if c.get("pose"):
            kw["pose"] = PoseSettings.from_dict(c["pose"])
        if c.get("move"):
            kw["move"] = {"offset_mm": float(c["move"]["offset_mm"]),
                          "tilt_deg": [float(a) for a in c["move"]["tilt_deg"]]}  # fmt: skip
        if c.get("subset") is not None:
            kw["subset"] = tuple(int(i) for i in c["subset"])
        return cls(**kw)

    def __post_init__(self):
        for name, bounds in (self.randomize or {}).items():
            if name not in NOMINAL or name in ("none", "dead_view") or len(bounds) != 2:
                raise SimulationError(
                    f"randomize.{name}: name a shift with a numeric strength and give [low, high]"
                )
            for x in bounds:
                Shift(name, x)  # each end a valid strength (one-line ShiftError otherwise)

    def scene_shifts(self, index: int, split: str | None) -> list[Shift]:
        """The shifts scene ``index`` renders under: ``shift``, and for a training scene of a
        randomized dataset, every randomized shift at a strength drawn for that scene."""
        if not self.randomize or split != "train":
            return [self.shift]
        rng = np.random.default_rng([self.seed, index, 2])
        drawn = [
            Shift(name, float(rng.uniform(lo, hi)), int(rng.integers(2**31)))
            for name, (lo, hi) in sorted(self.randomize.items())
        ]
        return [self.shift, *drawn]

    def indices(self) -> tuple[int, ...]:
        """The scene indices this dataset holds."""
        return tuple(range(self.scenes)) if self.subset is None else self.subset

    def complete(self) -> bool:
        """Whether ``out`` already holds every scene of this dataset."""
        scenes = self.out / "scenes"
        return (self.out / MANIFEST).is_file() and all(
            (scenes / scene_id(i)).is_dir() for i in self.indices()
        )

    def content_key(self) -> dict:
        """The settings that change pixels; a resumed run must match them."""
        return {
            "scenes": self.scenes,
            "family": self.family,
            "seed": self.seed,
            "images": self.images,
            "mix": self.mix,
            "mesh_dir": str(self.mesh_dir) if self.mesh_dir else None,
            "render": asdict(self.render),
            "fringe_dtype": self.fringe_dtype,
            # a nominal render keeps the key it had before shifts existed
            **({} if self.shift.nominal else {"shift": self.shift.to_dict()}),
            **({"randomize": self.randomize} if self.randomize else {}),
            # a fixed pose keeps the key it had before poses existed
            **({} if self.pose.fixed else {"pose": self.pose.to_dict()}),
            **({"move": self.move} if self.move else {}),
            **({"subset": list(self.subset)} if self.subset is not None else {}),
        }


def _scene_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([seed, index])


def scene_id(index: int) -> str:
    return f"{index:06d}"


def _split_labels(n: int, fractions: dict | None, seed: int) -> list[str | None]:
    """80/10/10-style labels from a seeded permutation (None when fractions is None)."""
    if not fractions:
        return [None] * n
    unknown = set(fractions) - set(SPLITS)
    if unknown:
        raise SimulationError(f"splits: unknown split name(s) {sorted(unknown)}; use {SPLITS}")
    w = np.array([fractions.get(s, 0.0) for s in SPLITS], float)
    counts = np.floor(w / w.sum() * n).astype(int)
    counts[0] += n - counts.sum()  # remainder goes to train
    labels = np.repeat(np.array(SPLITS, dtype=object), counts)
    perm = np.random.default_rng([seed, 2**31 - 1]).permutation(n)
    out = [None] * n
    for pos, idx in enumerate(perm):
        out[idx] = labels[pos]
    return out


def _manifest_for(s: SimSettings) -> Manifest:
    files = mesh_files_in(s.mesh_dir)
    labels = _split_labels(s.scenes, s.splits, s.seed)
    scenes = []
    for i in s.indices():
        family = choose_family(s.family, s.mix, _scene_rng(s.seed, i))
        if family == "freeform" and not files and s.mesh_dir:
            raise SimulationError(f"{s.mesh_dir}: no .stl/.obj/.ply files found")
        scene = {"id": scene_id(i), "split": labels[i], "family": family}
        drawn = [x.to_dict() for x in s.scene_shifts(i, labels[i])[1:]]
        pose = s.pose.draw(s.seed, i, family)
        scenes.append(
            scene | ({"shifts": drawn} if drawn else {}) | ({"pose": pose} if pose else {})
        )
    # scenes that move span a working volume of their own: the net's depth units follow it
    volume = {} if s.pose.fixed else {
        "depth_range_mm": list(s.pose.depth_range_mm(s.rig.camera.working_distance_mm))
    }  # fmt: skip
    return Manifest(
        root=s.out,
        height_px=s.height_px,
        width_px=s.width_px,
        views=s.views,
        # the sequence the rig projects; the uniform image only where the images are stored
        fringe=s.fringe if s.images == "full" else replace(s.fringe, uniform=False),
        rig=s.rig,
        images=s.images,
        scenes=scenes,
        extra={"simulation": s.content_key()} | volume,
    )


def without_phantom_uniform(m: Manifest) -> Manifest:
    """A manifest of network images only (images=training) that claims uniform images, as the
    simulator wrote them before it stopped doing so, with the claim dropped (and said); the
    simulator then rewrites it so, the dataset otherwise unchanged."""
    if m.images == "training" and m.fringe.uniform:
        print(f"{m.root / MANIFEST}: fringe.uniform set to false (images=training stores no "
              "uniform images)", flush=True)  # fmt: skip
        m.fringe = replace(m.fringe, uniform=False)
    return m


def draw_scene_spec(s: SimSettings, index: int, mesh_cache: dict | None = None) -> dict:
    """The spec of scene ``index``: family by the mix proportions, then the family's draw."""
    rng = _scene_rng(s.seed, index)
    family = choose_family(s.family, s.mix, rng)
    pose = s.pose.draw(s.seed, index, family)
    spec = draw_spec(family, rng, mesh_files_in(s.mesh_dir), mesh_cache, pose)
    return spec | ({"move": s.move} if s.move else {})


def render_and_write(s: SimSettings, index: int, spec: dict | None = None) -> str:
    """Render scene ``index`` and move it into place; returns its id."""
    sid = scene_id(index)
    final = s.out / "scenes" / sid
    if spec is None:
        spec = draw_scene_spec(s, index)
    scene = build_scene(spec)
    noise_seed = [s.seed, index, 1]
    split = _split_labels(s.scenes, s.splits, s.seed)[index]
    r = _render(
        scene,
        s.rig,
        s.height_px,
        s.width_px,
        s.fringe,
        s.views,
        s.render,
        s.scene_shifts(index, split),
        np.random.default_rng(noise_seed),
        s.images,
    )
    tmp = final.with_name(f"{PARTIAL_PREFIX}{sid}-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / FRINGE_DIR).mkdir(parents=True)
    dtype = np.dtype(s.fringe_dtype)
    for name, img in r.fringes.items():
        write_exr(tmp / FRINGE_DIR / name, {FRINGE_CHANNEL: img.astype(dtype)}, s.compression)
    write_exr(tmp / DEPTH_FILE, {DEPTH_CHANNEL: r.depth_mm}, s.compression)
    write_exr(tmp / LIT_FILE, {v: m.astype(np.float16) for v, m in r.lit.items()}, s.compression)
    foot = {v: m.astype(np.float16) for v, m in r.footprint.items()}
    write_exr(tmp / FOOTPRINT_FILE, foot, s.compression)
    write_exr(tmp / PROJ_COORD_FILE, r.projector_coord, s.compression)
    record = {
        "id": sid,
        "seed_sequence": [s.seed, index],
        "noise_seed_sequence": noise_seed,
        "spec": spec,
    }
    (tmp / SCENE_SPEC_FILE).write_text(json.dumps(record, indent=1) + "\n")
    os.rename(tmp, final)
    return sid


# Workers already fill every core: library thread pools inside them would only contend.
_SINGLE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@contextmanager
def _environment(values: dict[str, str]):
    """``values`` set in os.environ (where unset) only while the block runs: the spawned workers
    read them at import, and a caller that goes on to train (odmv.reproduce, the demo) must not
    inherit one thread for torch and every subprocess it starts."""
    added = {k: v for k, v in values.items() if k not in os.environ}
    os.environ.update(added)
    try:
        yield
    finally:
        for key in added:
            os.environ.pop(key, None)


@contextmanager
def _stops_ignored():
    """Processes started within ignore Ctrl-C and SIGTERM from birth (a disposition that
    survives exec, so it holds while a spawned worker still imports): a stop reaches the
    parent, which lets them finish their scene and then ends; had they died of it, each would
    print a traceback and the pool a third. A killed parent takes them along (die_with_parent)."""
    stops = (signal.SIGINT, signal.SIGTERM)
    before = [signal.signal(sig, signal.SIG_IGN) for sig in stops]
    try:
        yield
    finally:
        for sig, handler in zip(stops, before, strict=True):
            signal.signal(sig, handler)


def _worker_init(parent: int | None = None):
    OpenEXR.set_global_thread_count(0)
    die_with_parent(parent)


def scene_record(m: Manifest, sid: str) -> dict:
    """A stored scene's ``scene.json``: its spec and seed sequences."""
    return json.loads((m.scene_dir(sid) / SCENE_SPEC_FILE).read_text())


def render_config(m: Manifest) -> RenderConfig:
    """The render settings a synthetic dataset was written with (its manifest's record)."""
    return RenderConfig(**m.extra.get("simulation", {}).get("render", {}))


def shifts_of(m: Manifest, sid: str) -> list[Shift]:
    """The shifts a stored synthetic scene was rendered under (its manifest's records)."""
    base = Shift(**m.extra.get("simulation", {}).get("shift", {}))
    entry = next((s for s in m.scenes if s["id"] == sid), {})
    return [base, *(Shift(**d) for d in entry.get("shifts", []))]


def _render(scene, rig, height_px, width_px, fringe, views, cfg, shifts, rng, images):
    """render_scene through ``shifts``: their rig and optics, surfaces and dead projector."""
    a = apply(shifts, rig, cfg)
    return render_scene(
        scene,
        a.rig,
        height_px,
        width_px,
        fringe,
        views,
        a.render,
        rng,
        images,
        texture=a.texture,
        gloss=a.gloss,
        dead_view=a.dead_view,
    )


def rerender(root: str | Path, sid: str) -> tuple[Scene, Rendered]:
    """Render a stored scene again from its ``scene.json`` and the manifest (bit-identical)."""
    m = load_manifest(root)
    record = scene_record(m, sid)
    scene = build_scene(record["spec"])
    rng = np.random.default_rng(record["noise_seed_sequence"])
    r = _render(
        scene,
        m.rig,
        m.height_px,
        m.width_px,
        m.fringe,
        m.views,
        render_config(m),
        shifts_of(m, sid),
        rng,
        m.images,
    )
    return scene, r


def _worker(args):
    return render_and_write(*args)


@dataclass
class SimReport:
    rendered: int
    skipped: int
    seconds: float
    images: int


def simulate(
    s: SimSettings,
    workers: int | None = None,
    progress: bool = True,
    shard: tuple[int, int] | None = None,
) -> SimReport:
    """Render every missing scene of the dataset described by ``s`` (resumable); with
    ``shard=(i, n)`` only scenes i, i + n, i + 2n, ... (odmv.sim.shards joins the shards)."""
    try:
        s.views = check_views(s.views)
    except ValueError as e:
        raise SimulationError(f"views: {e}") from None
    if s.images not in ("full", "training"):
        raise SimulationError(f"images={s.images!r}: use 'full' or 'training'")
    if s.height_px < 16 or s.width_px < 16 or s.height_px % 16 or s.width_px % 16:
        raise SimulationError(
            f"resolution={s.height_px}x{s.width_px}: use positive multiples of 16 (px)"
        )
    if s.scenes < 1:
        raise SimulationError(f"scenes: {s.scenes}; render at least one scene")
    if s.subset is not None and not all(0 <= i < s.scenes for i in s.subset):
        raise SimulationError(f"subset: scene indices must lie in 0..{s.scenes - 1}")
    if s.mesh_dir:
        refuse_inside("out", [s.out], [s.mesh_dir])
    manifest = _manifest_for(s)
    if (s.out / MANIFEST).exists():
        old = without_phantom_uniform(load_manifest(s.out))
        if old.to_json() != manifest.to_json():
            raise SimulationError(
                f"{s.out / MANIFEST}: this folder holds a dataset made with other settings; "
                "choose another out= or delete the folder"
            )
    elif s.out.exists() and any(s.out.iterdir()):
        raise SimulationError(f"{s.out}: folder exists, is not empty and has no {MANIFEST}")
    scenes_dir = s.out / "scenes"
    mine = s.indices() if shard is None else s.indices()[shard[0] :: shard[1]]
    todo = [i for i in mine if not (scenes_dir / scene_id(i)).is_dir()]
    skipped = len(mine) - len(todo)
    need = scene_bytes_bound(s) * len(todo)
    big = need > BIG_JOB_BYTES
    if todo:
        check_disk(s.out, need, len(todo), announce=big)
    # specs are drawn before anything is written, so a bad mesh file leaves no folder behind
    cache: dict = {}
    specs = {i: draw_scene_spec(s, i, cache) for i in todo}
    workers = max(1, min(workers or os.cpu_count() or 1, len(todo) or 1))
    scenes_dir.mkdir(parents=True, exist_ok=True)
    for i in mine:  # left by an interrupted run (another shard's are not this run's)
        for stale in scenes_dir.glob(f"{PARTIAL_PREFIX}{scene_id(i)}-*"):
            shutil.rmtree(stale)
    manifest.write()
    t0 = time.perf_counter()
    if big and len(todo) > 1:  # time one scene, then say how long the rest will take
        first = todo.pop(0)
        render_and_write(s, first, specs[first])
        per_scene = time.perf_counter() - t0
        print(
            f"first scene: {per_scene:.1f} s; the other {len(todo)} take about "
            f"{_duration(per_scene * len(todo) / workers)} with {workers} workers",
            flush=True,
        )
    columns = (TextColumn("rendering"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns, disable=not progress) as bar:
        task = bar.add_task("scenes", total=len(todo))
        if workers == 1:
            for i in todo:
                render_and_write(s, i, specs[i])
                bar.advance(task)
        else:
            ctx = get_context("spawn")
            with _environment(_SINGLE_THREAD_ENV):
                pool = ProcessPoolExecutor(
                    workers, ctx, initializer=_worker_init, initargs=(os.getpid(),)
                )
            try:
                with _stops_ignored():  # the workers are spawned by map's submissions
                    done = pool.map(_worker, [(s, i, specs[i]) for i in todo])
                for _ in done:
                    bar.advance(task)
            finally:  # stopped: the scenes in progress finish, the rest are never started
                pool.shutdown(wait=True, cancel_futures=True)
    seconds = time.perf_counter() - t0
    rendered = len(mine) - skipped
    per_scene = len(manifest.fringe_files(scene_id(0)))
    return SimReport(rendered, skipped, seconds, per_scene * rendered)


#: Jobs whose files may exceed this print their size, time and the free disk space first.
BIG_JOB_BYTES = 2 * 1024**3


def scene_bytes_bound(s: SimSettings) -> int:
    """Bytes of one scene's files before compression: an upper bound, as the fringes'
    photon noise leaves lossless compression little to gain."""
    pixels = s.height_px * s.width_px
    n_views = len(s.views)
    f = s.fringe
    per_view = len(f.periods_px) * f.steps + int(f.uniform) if s.images == "full" else 1
    fringes = n_views * per_view * pixels * np.dtype(s.fringe_dtype).itemsize
    # depth (float32), lit and footprint masks (float16 per view), projector coordinate (float32)
    return fringes + pixels * (4 + n_views * (2 + 2 + 4))


def check_disk(out: Path, need_bytes: int, scenes: int, announce: bool) -> None:
    """Refuse a job that the disk under ``out`` cannot hold; announce a big one."""
    probe = out
    while not probe.exists():
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need_bytes > free:
        raise SimulationError(
            f"{out}: {scenes} scenes need up to {human_size(need_bytes)} but only "
            f"{human_size(free)} are free there (choose another out=, fewer scenes, "
            "images=training or fringe_dtype=float16)"
        )
    if announce:
        print(
            f"{out}: {scenes} scenes, up to {human_size(need_bytes)} "
            f"({human_size(need_bytes / scenes)} each); {human_size(free)} free",
            flush=True,
        )


def human_size(n_bytes: float) -> str:
    return f"{n_bytes / 1e9:.1f} GB" if n_bytes >= 1e9 else f"{n_bytes / 1e6:.1f} MB"


def _duration(seconds: float) -> str:
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.0f} min"
