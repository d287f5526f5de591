"""Training-step time and peak memory of a preset's net: forward, composite loss, backward,
gradient clipping and an Adam step (the preset's optimizer settings) on a synthetic batch of
the preset's shapes.

    python experiments/bench_train.py --preset paper --model odmvnet            # 480 px, batch 2
    python experiments/bench_train.py --preset paper --device cuda --precision bf16-mixed \\
        --channels-last --cudnn-benchmark --compile
    python experiments/bench_train.py --preset quickstart --steps 20            # the demo's net

Prints the median step time over --steps steps after --warmup steps, samples/s, and peak
memory (CUDA: max allocated; CPU: peak RSS of this process). Any training override goes after
--set, e.g. --set views=2 data.resolution=256 model.net.activation_checkpointing=true.

On a shared 2-core machine runs of one configuration differ by up to 40 %, so compare
configurations alternated, each in a fresh process, in ABBA order:

    python experiments/bench_train.py --preset mini --rounds 3 \
        --variants "--precision 32" "--precision bf16-mixed"
"""

from __future__ import annotations

import argparse
import re
import shlex
import statistics
import subprocess
import sys
import time

import torch
from omegaconf import OmegaConf

from odmv.cli import quiet_lightning
from odmv.training.bench import (
    PRESETS,
    build_module,
    input_size,
    peak_memory,
    percentile,
    preset_config,
    sync,
    synthetic_batch,
)
from odmv.training.losses import LossWeights, composite_loss
from odmv.training.module import make_optimizer, net_input


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="paper", choices=PRESETS)
    ap.add_argument("--model", default="odmvnet", help="odmvnet, unet, hnet, uhrnet or mtlnet")
    ap.add_argument("--batch", type=int, default=None, help="default: the preset's batch size")
    ap.add_argument("--resolution", type=int, default=None, help="default: the preset's size")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--precision", default="32", choices=("32", "bf16-mixed", "16-mixed"))
    ap.add_argument(
        "--channels-last",
        action="store_true",
        help="channels_last(_3d) weights in 2D layers too (ODMV-Net's 3D ones are by default)",
    )
    ap.add_argument("--compile", action="store_true", help="torch.compile the net")
    ap.add_argument("--compile-mode", default="max-autotune-no-cudagraphs")
    ap.add_argument("--cudnn-benchmark", action="store_true")
    ap.add_argument("--checkpointing", action="store_true", help="activation checkpointing")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--set", nargs="*", default=[], help="more training overrides")
    ap.add_argument(
        "--variants",
        nargs="+",
        default=None,
        help="compare these argument sets (each a quoted string added to the others)",
    )
    ap.add_argument("--rounds", type=int, default=3, help="with --variants: ABBA rounds")
    args = ap.parse_args()
    if args.variants:
        compare(args.variants, args.rounds)
        return
    quiet_lightning()  # the deprecation notes Lightning and torch.export raise

    overrides = list(args.set)
    if args.resolution:
        overrides.append(f"data.resolution={args.resolution}")
    if args.checkpointing:
        overrides.append("model.net.activation_checkpointing=true")
    cfg = preset_config(args.preset, args.model, overrides)
    batch_size = args.batch or cfg.data.batch_size
    device = torch.device(args.device)
    torch.backends.cudnn.benchmark = args.cudnn_benchmark
    module = build_module(cfg).to(device).train()
    if args.channels_last:  # every conv weight, 2D and 3D (Module.to refuses a mix of ranks)
        for p in module.parameters():
            if p.ndim in (4, 5):
                fmt = torch.channels_last if p.ndim == 4 else torch.channels_last_3d
                p.data = p.data.contiguous(memory_format=fmt)
    net = torch.compile(module.net, mode=args.compile_mode) if args.compile else module.net
    weights = LossWeights(**cfg.loss)
    opt = make_optimizer(module.parameters(), OmegaConf.to_container(cfg.optimizer, resolve=True))
    batch = synthetic_batch(cfg, batch_size, device)
    dtype = {"bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}.get(args.precision)
    scaler = torch.amp.GradScaler(device.type, enabled=args.precision == "16-mixed")

    def step() -> None:
        with torch.autocast(device.type, dtype=dtype, enabled=dtype is not None):
            loss = composite_loss(net(net_input(batch)), batch, weights)["loss"]
        scaler.scale(loss).backward()
        scaler.unscale_(opt)
        torch.nn.utils.clip_grad_norm_(module.parameters(), 1.0)
        scaler.step(opt)
        scaler.update()
        opt.zero_grad(set_to_none=True)

    for _ in range(args.warmup):
        step()
    sync(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    times = []
    for _ in range(args.steps):
        t0 = time.perf_counter()
        step()
        sync(device)
        times.append(time.perf_counter() - t0)
    h, w = input_size(cfg)
    median = statistics.median(times)
    switches = [
        name
        for name, on in (
            ("channels_last", args.channels_last),
            (f"compile({args.compile_mode})", args.compile),
            ("cudnn.benchmark", args.cudnn_benchmark),
            ("activation checkpointing", args.checkpointing),
        )
        if on
    ]
    params = sum(p.numel() for p in module.net.parameters())
    print(
        f"{args.model} ({params / 1e6:.1f} M parameters), preset {args.preset}, "
        f"{len(cfg.data.views)} views, {h}x{w}, batch {batch_size}, {args.precision}, "
        f"{device}{', ' + ', '.join(switches) if switches else ''}:\n"
        f"  step {median * 1e3:.1f} ms median (p95 {percentile(times, 95) * 1e3:.1f} ms, "
        f"{args.steps} steps after {args.warmup}), {batch_size / median:.2f} samples/s, "
        f"{peak_memory(device)}"
    )


def compare(variants: list[str], rounds: int) -> None:
    """Each variant ``rounds`` times in a fresh process, the order reversed every other round
    (ABBA), with this call's other arguments; then the median step of each variant's runs."""
    base, argv = [], iter(sys.argv[1:])
    for a in argv:
        if a == "--rounds":
            next(argv)
        elif a != "--variants" and a not in variants:
            base.append(a)
    steps: dict[str, list[float]] = {v: [] for v in variants}
    for r in range(rounds):
        for v in variants if r % 2 == 0 else variants[::-1]:
            cmd = [sys.executable, __file__, *base, *shlex.split(v)]
            out = subprocess.run(cmd, capture_output=True, text=True)
            if out.returncode:
                lines = out.stderr.strip().splitlines()
                errors = [x for x in lines if re.match(r"(\S+(Error|Exception): |error)", x)]
                why = (errors or lines or [f"exit {out.returncode}"])[-1]
                raise SystemExit(f"error: {shlex.join(cmd)}: {why}")
            ms = float(out.stdout.split("step ")[1].split(" ms")[0])
            steps[v].append(ms)
            print(f"round {r + 1}: {v}: {ms:.1f} ms", flush=True)
    for v, ms in steps.items():
        print(
            f"{v}: median {statistics.median(ms):.1f} ms over {len(ms)} runs "
            f"({', '.join(f'{m:.1f}' for m in ms)})"
        )


if __name__ == "__main__":
    main()
