"""ODMV-Net size and speed: parameter counts (paper preset, per module, per Table I row) and,
optionally, forward time on this machine.

    python experiments/model_summary.py                 # counts only (no memory needed)
    python experiments/model_summary.py --time 480      # + CPU forward at 480x480x4, batch 1
"""

from __future__ import annotations

import argparse
import time

import torch

from odmv.models import ABLATION_ROWS, ODMVNet, count_parameters, parameter_breakdown

PAPER = 112_560_408


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base-width", type=int, default=46)
    ap.add_argument("--time", type=int, default=0, help="time a forward pass at this size")
    ap.add_argument("--views", type=int, default=4)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    with torch.device("meta"):
        net = ODMVNet(base_width=args.base_width)
        total = count_parameters(net)
        print(
            f"ODMV-Net base_width={args.base_width}: {total:,} parameters "
            f"({(total / PAPER - 1) * 100:+.2f} % of the paper's {PAPER:,})"
        )
        for name, n in parameter_breakdown(net).items():
            if n:
                print(f"  {name:12s} {n:>12,}  {n / total * 100:5.1f} %")
        print("Table I rows:")
        for row in ABLATION_ROWS:
            print(f"  {row:10s} {count_parameters(ODMVNet(args.base_width, ablation=row)):>12,}")
    if args.time:
        torch.manual_seed(0)
        net = ODMVNet(base_width=args.base_width).eval()
        x = torch.rand(1, args.views, args.time, args.time) * 2 - 1
        with torch.inference_mode():
            net(x)  # warm-up
            t0 = time.perf_counter()
            for _ in range(args.repeats):
                net(x)
        dt = (time.perf_counter() - t0) / args.repeats
        print(
            f"forward {args.time}x{args.time}x{args.views}, batch 1, "
            f"{torch.get_num_threads()} threads: {dt:.2f} s"
        )


if __name__ == "__main__":
    main()
