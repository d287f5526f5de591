"""A dataset rendered in shards, e.g. one per cluster node: ``shard=I/N`` renders scenes
I, I + N, I + 2N, ... (odmv.sim.writer.simulate), and :func:`merge` joins the shards' folders
into the dataset one unsharded run writes, byte for byte.

Shards may also share one folder (a shared file system): each writes only its own scenes and
the same manifest, so the folder is the whole dataset once every shard has finished.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from odmv.io.guard import refuse_inside
from odmv.io.manifest import MANIFEST, Manifest, ManifestError, load_manifest
from odmv.sim.writer import SimulationError


def parse_shard(text) -> tuple[int, int] | None:
    """``"I/N"`` -> (I, N), with 0 <= I < N; None stays None."""
    if text is None:
        return None
    index, sep, count = str(text).partition("/")
    try:
        i, n = int(index), int(count)
    except ValueError:
        i, n = -1, 0
    if not sep or not 0 <= i < n:
        raise SimulationError(f"shard={text}: use I/N with 0 <= I < N, e.g. shard=0/4")
    return i, n


def shard_ids(m: Manifest, shard: tuple[int, int]) -> list[str]:
    """The scene ids of one shard of the dataset ``m`` describes."""
    return [s["id"] for s in m.scenes[shard[0] :: shard[1]]]


def merge(dirs: list[str | Path], out: str | Path) -> Manifest:
    """Join shard folders of one dataset (equal manifests, every scene in one of them) into
    ``out``, which must not exist; the shards stay as they are."""
    dirs, out = [Path(d) for d in dirs], Path(out)
    if not dirs:
        raise SimulationError("merge: name the shard folders, merge=[DIR,...]")
    if out.exists():
        raise SimulationError(f"{out}: exists; merge writes a new folder (choose another out=)")
    refuse_inside("out", [out], dirs)
    manifests = []
    for d in dirs:
        try:
            manifests.append(load_manifest(d))
        except ManifestError as e:
            raise SimulationError(f"merge: {e}") from None
    first = manifests[0]
    for d, m in zip(dirs[1:], manifests[1:], strict=True):
        if m.to_json() != first.to_json():
            raise SimulationError(f"{d / MANIFEST}: another dataset than {dirs[0] / MANIFEST}")
    where = {}
    for d in dirs:
        for scene in sorted((d / "scenes").glob("[!.]*")):
            where.setdefault(scene.name, scene)
    missing = [s["id"] for s in first.scenes if s["id"] not in where]
    if missing:
        raise SimulationError(
            f"merge: {len(missing)} scene(s) in none of the shards (first {missing[0]}): "
            "render the missing shards first"
        )
    tmp = out.with_name(f".{out.name}.partial")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        for s in first.scenes:
            shutil.copytree(where[s["id"]], tmp / "scenes" / s["id"])
        shutil.copy2(dirs[0] / MANIFEST, tmp / MANIFEST)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return load_manifest(out)
