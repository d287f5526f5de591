"""Per-layer convolution times of a preset's net: every 2D and 3D convolution of one training
forward (transposed ones not included), replayed alone at its real shapes, memory format and
precision (forward and both backward passes), with its achieved GFLOP/s; layers of the same
shape are timed once.

    python experiments/bench_convs.py --preset mini --model odmvnet
    python experiments/bench_convs.py --preset mini --model odmvnet --precision bf16 --im2col

It shows which layers hold a training step back: the sum is what the convolutions would cost
if nothing else ran. ``--im2col`` times each 3D layer also as one GEMM over the gathered
taps (autograd differentiates the gather), the lowering a small-spatial, many-channel layer
might prefer to oneDNN's direct convolution.
"""

from __future__ import annotations

import argparse
import collections
import statistics

import torch
import torch.nn as nn
import torch.nn.functional as F

from odmv.cli import quiet_lightning
from odmv.models.blocks import _ReachableTaps, reachable_taps
from odmv.training.bench import PRESETS, build_module, measure, preset_config, synthetic_batch
from odmv.training.module import net_input

Layer = collections.namedtuple("Layer", "x_shape w_shape padding stride dilation groups x_cl w_cl")


def record_layers(net: nn.Module, batch) -> collections.Counter:
    """The convolutions one forward runs, as the kernel sees them (taps that only meet padding
    dropped, as the net's own layers do), with how often each occurs."""
    seen: collections.Counter = collections.Counter()

    def hook(mod, args):
        x = args[0]
        w, pad = mod.weight, mod.padding
        if isinstance(mod, _ReachableTaps):
            w, pad = reachable_taps(w, x.shape[2:], pad, mod.dilation, mod.stride)
        fmt = torch.channels_last_3d if x.dim() == 5 else torch.channels_last
        seen[
            Layer(
                tuple(x.shape),
                tuple(w.shape),
                tuple(pad),
                tuple(mod.stride),
                tuple(mod.dilation),
                mod.groups,
                x.is_contiguous(memory_format=fmt) and not x.is_contiguous(),
                w.is_contiguous(memory_format=fmt) and not w.is_contiguous(),
            )
        ] += 1

    convs = [m for m in net.modules() if isinstance(m, (nn.Conv2d, nn.Conv3d))]
    handles = [m.register_forward_pre_hook(hook) for m in convs]
    try:
        with torch.no_grad():
            net(net_input(batch))
    finally:
        for h in handles:
            h.remove()
    return seen


def im2col_conv3d(x, w, padding, dilation):
    """A stride-1, ungrouped 3D convolution as one GEMM: the taps gathered channels-last."""
    b, _, s, h, wd = x.shape
    cout, cin, *k = w.shape
    xp = F.pad(
        x.permute(0, 2, 3, 4, 1),
        (0, 0, padding[2], padding[2], padding[1], padding[1], padding[0], padding[0]),
    )
    cols = torch.cat(
        [
            xp[
                :,
                i * dilation[0] : i * dilation[0] + s,
                j * dilation[1] : j * dilation[1] + h,
                m * dilation[2] : m * dilation[2] + wd,
            ]
            for i in range(k[0])
            for j in range(k[1])
            for m in range(k[2])
        ],
        dim=-1,
    )
    y = cols.reshape(-1, cols.shape[-1]) @ w.permute(2, 3, 4, 1, 0).reshape(-1, cout)
    return y.view(b, s, h, wd, cout).permute(0, 4, 1, 2, 3)


def median_ms(fn, reps: int) -> float:
    return statistics.median(measure(fn, reps, 2, torch.device("cpu"))) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="mini", choices=PRESETS)
    ap.add_argument("--model", default="odmvnet")
    ap.add_argument("--batch", type=int, default=None, help="default: the preset's batch size")
    ap.add_argument("--precision", default="32", choices=("32", "bf16"))
    ap.add_argument("--im2col", action="store_true", help="also time 3D layers as one GEMM")
    ap.add_argument("--reps", type=int, default=8)
    ap.add_argument("--set", nargs="*", default=[], help="more training overrides")
    args = ap.parse_args()
    quiet_lightning()

    cfg = preset_config(args.preset, args.model, list(args.set))
    batch = synthetic_batch(cfg, args.batch or cfg.data.batch_size, torch.device("cpu"))
    layers = record_layers(build_module(cfg).train().net, batch)
    dtype = torch.bfloat16 if args.precision == "bf16" else torch.float32
    print(
        f"{args.model}, preset {args.preset}, {args.precision}, {torch.get_num_threads()} "
        f"threads: each convolution's forward + backward (input and weight gradients)"
    )
    total = total_alt = 0.0
    for layer, count in sorted(layers.items(), key=lambda kv: -kv[0].x_shape[-1]):
        ms, alt, gflop = time_layer(layer, dtype, args.reps, args.im2col)
        line = (
            f"  x {layer.x_shape} w {layer.w_shape} pad {layer.padding} dil {layer.dilation} "
            f"groups {layer.groups}{' cl' if layer.x_cl else ''} x{count}: {ms:.2f} ms, "
            f"{gflop / ms * 1e3:.0f} GFLOP/s"
        )
        if alt is not None:
            line += f"; im2col {alt:.2f} ms"
        print(line)
        total += ms * count
        total_alt += min(ms, alt if alt is not None else ms) * count
    summary = f"all convolutions: {total:.1f} ms per step"
    if args.im2col:
        summary += f"; with im2col wherever it is faster: {total_alt:.1f} ms"
    print(summary)


def time_layer(layer: Layer, dtype, reps: int, im2col: bool):
    """Median ms of the layer's forward + backward, the same lowered to im2col (or None), and
    its GFLOP (forward, input gradient and weight gradient)."""
    dims = len(layer.x_shape) - 2
    fmt = torch.channels_last_3d if dims == 3 else torch.channels_last
    x = torch.randn(layer.x_shape, dtype=dtype)
    w = torch.randn(layer.w_shape, dtype=dtype)
    x = (x.contiguous(memory_format=fmt) if layer.x_cl else x).requires_grad_()
    w = (w.contiguous(memory_format=fmt) if layer.w_cl else w).requires_grad_()
    conv = F.conv3d if dims == 3 else F.conv2d

    def direct():
        return conv(x, w, None, layer.stride, layer.padding, layer.dilation, layer.groups)

    y = direct()
    grad = torch.randn_like(y)
    ms = median_ms(lambda: direct().backward(grad), reps)
    gflop = 3 * 2 * y[0, 0].numel() * y.shape[0] * w.numel() / 1e9
    alt = None
    if im2col and dims == 3 and layer.groups == 1 and layer.stride == (1, 1, 1):
        lowered = im2col_conv3d(x, w, layer.padding, layer.dilation)
        err = (lowered - y).abs().max().item()
        if err > 1e-2 * y.abs().max().item():
            raise SystemExit(f"im2col disagrees with the convolution at {layer}: {err}")
        alt = median_ms(
            lambda: im2col_conv3d(x, w, layer.padding, layer.dilation).backward(grad), reps
        )
    return ms, alt, gflop


if __name__ == "__main__":
    main()
