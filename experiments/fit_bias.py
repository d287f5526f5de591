"""What the label-free loss asks of the true depth: on twin scenes (which have it), the depth
change (mm) each view's fringe fit asks for at the truth, for several fits. A fit whose
optimum is the truth asks for nothing; what it asks for there, it teaches a net that adapts
with it (odmv/training/consistency.py, experiments/results/adapt/notebook.md).

    python experiments/fit_bias.py data/adapt100-seed3-gamma_2.2-* --scenes 24 \
        --fits 5:1 7:1 9:1 7:2 9:2

Per dataset and fit (window px : harmonics): each view's weighted mean asked-for change (the
bias: what moves a whole view), the weighted mean of its magnitude (what pulls each pixel),
and the share of view pixels with weight; first, per dataset, each view's second harmonic
against its fundamental (what ``adaptation.harmonics=auto`` looks at), with ``--run CKPT``
also over all views under that net's depth, as the adaptation measures it.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from odmv.classical.geometry import triangulation_maps
from odmv.data.dataset import check_spec, load_scene
from odmv.io.manifest import load_manifest
from odmv.training.adaptation import second_harmonic_share
from odmv.training.consistency import ConsistencySettings, harmonic_sums, view_corrections_mm
from odmv.training.evaluation import checkpoint_datamodule
from odmv.training.module import load_module


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("datasets", nargs="+", help="twin dataset folders (with depth)")
    p.add_argument("--scenes", type=int, default=24, help="the first N scenes of each")
    p.add_argument("--size", type=int, default=64, help="image size (px)")
    p.add_argument("--fits", nargs="+", default=["5:1", "9:1", "9:2"], help="WINDOW:HARMONICS")
    p.add_argument("--run", help="a checkpoint: the second harmonic also under its depth")
    a = p.parse_args()
    torch.set_num_threads(1)
    module = load_module(a.run) if a.run else None
    for root in a.datasets:
        if module is not None:  # what harmonics=auto sees: a net's depth, no truth
            dm = checkpoint_datamodule(module, None, root=root, calibration=True, batch_size=4)
            module.norm = dm.norm
            batches = -(-a.scenes // 4)
            loader = dm.train_dataloader() if dm.splits.get("train") else dm.test_dataloader()
            share = second_harmonic_share(module, loader, ConsistencySettings(), batches)
            print(f"{root}  second / first harmonic under the run's depth: {share:.3f}", flush=True)
        m = load_manifest(root)
        spec = check_spec(m, m.views, a.size, None, None)
        maps = triangulation_maps(
            m.rig, m.views, a.size, a.size, spec.period_px, spec.step, spec.n_steps
        )
        scenes = [load_scene(m, s["id"], spec) for s in m.scenes[: a.scenes]]
        maps = torch.from_numpy(maps)[None].expand(len(scenes), -1, -1, -1, -1)
        fringes = torch.from_numpy(np.stack([s["fringes"] for s in scenes]))
        truth = torch.from_numpy(np.stack([s["depth_mm"] for s in scenes]))
        known = torch.isfinite(truth)
        truth = torch.where(known, truth, truth.nanmean())
        second, first = harmonic_sums(truth, fringes, maps, ConsistencySettings())
        ratios = ", ".join(
            f"{v} {float(r):.3f}" for v, r in zip(m.views, second / first, strict=True)
        )
        print(f"{root}  second / first harmonic at the truth: {ratios}", flush=True)
        for fit in a.fits:
            window, harmonics = (int(x) for x in fit.split(":"))
            settings = ConsistencySettings(window_px=window, harmonics=harmonics)
            change, w = view_corrections_mm(truth, fringes, maps, settings)
            w = w * known  # pixels without a true depth carry no weight
            bias = (w * change).sum((0, 2, 3)) / w.sum((0, 2, 3))
            pull = float((w * change.abs()).sum() / w.sum())
            views = ", ".join(f"{v} {float(b):+.4f}" for v, b in zip(m.views, bias, strict=True))
            print(
                f"{root}  window {window} harmonics {harmonics}: bias {views} mm; "
                f"mean |change| {pull:.4f} mm; weighted {float((w > 0).float().mean()):.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
