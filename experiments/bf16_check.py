"""bf16 correctness of a preset's net: from the same weights and batch, one training step in
float32 and one in bf16 autocast (Lightning's bf16-mixed: float32 weights and optimizer). The
losses must agree to --tolerance relative; the gradients' cosine similarity is printed beside
them (tiny nets on random batches give about 0.95 in bf16 on the CPU), and the depth error
after the step, in mm, is computed from the float32 cast of each net's output.

    python experiments/bf16_check.py --preset paper_plus --device cuda
    python experiments/bf16_check.py --preset quickstart --resolution 32 --batch 1   # CPU, tiny

Exits 1 when the losses disagree.
"""

from __future__ import annotations

import argparse
import copy
import sys

import torch
from omegaconf import OmegaConf

from odmv.cli import quiet_lightning
from odmv.training.bench import PRESETS, build_module, preset_config, synthetic_batch
from odmv.training.losses import LossWeights, composite_loss
from odmv.training.module import make_optimizer, net_input


def run(module, batch, weights, opt_cfg, bf16: bool, device) -> tuple[float, torch.Tensor, float]:
    """One training step: its loss, its gradient (flattened) and the depth MAE (mm) after it."""
    opt = make_optimizer(module.parameters(), opt_cfg)
    with torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
        loss = composite_loss(module.net(net_input(batch)), batch, weights)["loss"]
    loss.backward()
    grad = torch.cat([p.grad.flatten() for p in module.parameters() if p.grad is not None])
    torch.nn.utils.clip_grad_norm_(module.parameters(), 1.0)
    opt.step()
    module.eval()
    with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=bf16):
        depth = module.net(net_input(batch))["depth"]
    mm = module.norm.depth_mm(depth.float()) - module.norm.depth_mm(batch["depth"].float())
    return float(loss.detach()), grad.float(), float(mm.abs().mean())


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="paper_plus", choices=PRESETS)
    ap.add_argument("--model", default="odmvnet")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--resolution", type=int, default=None, help="default: the preset's size")
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--tolerance", type=float, default=1e-2, help="relative, per step")
    ap.add_argument("--set", nargs="*", default=[], help="more training overrides")
    args = ap.parse_args()
    quiet_lightning()

    overrides = list(args.set)
    if args.resolution:
        overrides.append(f"data.resolution={args.resolution}")
    cfg = preset_config(args.preset, args.model, overrides)
    device = torch.device(args.device)
    torch.manual_seed(0)
    base = build_module(cfg).to(device).train()
    batch = synthetic_batch(cfg, args.batch, device)
    weights = LossWeights(**cfg.loss)
    opt_cfg = OmegaConf.to_container(cfg.optimizer, resolve=True)
    results = {
        name: run(copy.deepcopy(base), batch, weights, opt_cfg, bf16, device)
        for name, bf16 in (("float32", False), ("bf16-mixed", True))
    }
    (l32, g32, mae32), (l16, g16, mae16) = results["float32"], results["bf16-mixed"]
    rel = abs(l16 - l32) / max(abs(l32), 1e-12)
    cosine = float(torch.nn.functional.cosine_similarity(g32, g16, dim=0))
    print(f"{args.model}, preset {args.preset}, {device}, batch {args.batch}:")
    print(f"  loss: float32 {l32:.6f}, bf16-mixed {l16:.6f}, relative difference {rel:.2e}")
    print(f"  gradient cosine similarity {cosine:.5f}")
    print(f"  depth MAE after the step: float32 {mae32:.4f} mm, bf16-mixed {mae16:.4f} mm")
    ok = rel <= args.tolerance
    print(f"  bf16 {'agrees' if ok else 'DISAGREES'} (loss tolerance {args.tolerance})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
