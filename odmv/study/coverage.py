"""Where each view set of the view-count experiment has a fringe, on one split of a dataset.

    python -m odmv.study coverage data/synthetic-200x64px-4609dd24 [--split test]

For each view set of odmv.rig.VIEW_SETS, the share of the valid pixels (finite depth) that some
projector lights but none of the set's views does: the pixels where adding views can bring a
fringe. They are split into those inside one of the set's footprints (occlusion hides them) and
those outside every footprint of the set (the field's edge hides them). From the dataset's
lit.exr and footprint.exr at its stored size; prints a markdown table.
"""

from __future__ import annotations

import argparse

import numpy as np

from odmv.data.dataset import split_scenes
from odmv.io.exr import ExrError, read_exr
from odmv.io.manifest import (
    DEPTH_CHANNEL,
    DEPTH_FILE,
    FOOTPRINT_FILE,
    LIT_FILE,
    ManifestError,
    load_manifest,
)
from odmv.rig import VIEW_SETS


def coverage(root: str, split: str) -> tuple[int, dict[int, np.ndarray]]:
    """Scenes counted, and per view count: pixels (valid, missed in footprint, missed outside)."""
    m = load_manifest(root)
    if not set(VIEW_SETS[4]) <= set(m.views):
        raise SystemExit(f"error: {root}: holds the views {list(m.views)}, not all four")
    ids = split_scenes(m, None, 0)[split]
    counts = {s: np.zeros(3, np.int64) for s in VIEW_SETS}
    for sid in ids:
        d = m.scene_dir(sid)
        lit = {v: a > 0.5 for v, a in read_exr(d / LIT_FILE, m.views).items()}
        foot = {v: a > 0.5 for v, a in read_exr(d / FOOTPRINT_FILE, m.views).items()}
        valid = np.isfinite(read_exr(d / DEPTH_FILE, [DEPTH_CHANNEL])[DEPTH_CHANNEL])
        lit_any = np.any(list(lit.values()), 0)
        for s, views in VIEW_SETS.items():
            missed = valid & lit_any & ~np.any([lit[v] for v in views], 0)
            inside = np.any([foot[v] for v in views], 0)
            counts[s] += [valid.sum(), (missed & inside).sum(), (missed & ~inside).sum()]
    return len(ids), counts


def main(argv: list[str]) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("--split", default="test", choices=("train", "val", "test"))
    args = ap.parse_args(argv)
    try:
        n, counts = coverage(args.dataset, args.split)
    except (ManifestError, ExrError, FileNotFoundError) as e:
        raise SystemExit(f"error: {e}") from None
    print(f"{args.dataset}, {args.split} split ({n} scenes); % of the valid pixels")
    print("| views | no fringe in the set, lit by another | inside its footprints | outside them |")
    print("|---|---:|---:|---:|")
    for s, views in sorted(VIEW_SETS.items()):
        valid, inside, outside = counts[s]
        share = [100 * x / max(valid, 1) for x in (inside + outside, inside, outside)]
        print(f"| S={s} ({', '.join(views)}) | " + " | ".join(f"{x:.1f}" for x in share) + " |")
