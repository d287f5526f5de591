"""Inference latency of a preset's net: per frame (p50, p95) and frames/s, at batch 1 and a
larger batch, for PyTorch eager, torch.compile and ONNX Runtime (the graph odmv.export writes).

    python experiments/bench_infer.py --preset paper --model odmvnet        # 480 px, 4 views
    python experiments/bench_infer.py --preset paper --device cuda --precision bf16 --batches 1 8
    python experiments/bench_infer.py --preset quickstart --runtimes eager onnx

A frame is one set of S view images in, one depth map (mm) out. Weights are random: latency
does not depend on them. ONNX Runtime uses CUDA when --device cuda and it is available.
"""

from __future__ import annotations

import argparse
import tempfile
from functools import partial
from pathlib import Path

import numpy as np
import torch

from odmv.cli import quiet_lightning
from odmv.deploy.onnx import DepthInMM, export_graph
from odmv.training.bench import (
    PRESETS,
    build_module,
    input_size,
    measure,
    percentile,
    preset_config,
    synthetic_batch,
)
from odmv.training.module import net_input


def _onnx_session(model: torch.nn.Module, example: torch.Tensor, device: torch.device):
    import onnx
    import onnxruntime as ort

    path = Path(tempfile.mkdtemp(prefix="odmv-bench-")) / "model.onnx"
    onnx.save(export_graph(model.cpu(), example.cpu()), path)
    providers = ["CPUExecutionProvider"]
    if device.type == "cuda" and "CUDAExecutionProvider" in ort.get_available_providers():
        providers.insert(0, "CUDAExecutionProvider")
    model.to(device)
    return ort.InferenceSession(str(path), providers=providers), providers[0]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="paper", choices=PRESETS)
    ap.add_argument("--model", default="odmvnet")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--precision", default="32", choices=("32", "bf16"), help="eager/compiled")
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 4])
    ap.add_argument("--runtimes", nargs="+", default=["eager", "compiled", "onnx"])
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--set", nargs="*", default=[], help="more training overrides")
    args = ap.parse_args()
    quiet_lightning()  # the deprecation notes Lightning and torch.export raise

    cfg = preset_config(args.preset, args.model, list(args.set))
    device = torch.device(args.device)
    module = build_module(cfg).eval()
    model = DepthInMM(module).to(device).eval()
    dtype = torch.bfloat16 if args.precision == "bf16" else None
    h, w = input_size(cfg)
    params = sum(p.numel() for p in module.net.parameters())
    print(
        f"{args.model} ({params / 1e6:.1f} M parameters), preset {args.preset}, "
        f"{len(cfg.data.views)} views, {h}x{w}, {device}, precision {args.precision}:"
    )
    runners = {}
    example = net_input(synthetic_batch(cfg, 2, device))
    if "eager" in args.runtimes:
        runners["eager"] = model
    if "compiled" in args.runtimes:
        runners["compiled"] = torch.compile(model, mode="max-autotune-no-cudagraphs")
    session = provider = None
    if "onnx" in args.runtimes:
        session, provider = _onnx_session(model, example, device)
    for batch in args.batches:
        x = net_input(synthetic_batch(cfg, batch, device))
        for name, fn in runners.items():
            _report(
                name, batch, measure(_torch_call(fn, x, dtype), args.repeats, args.warmup, device)
            )
        if session is not None:
            feed = {"inputs": x.cpu().numpy().astype(np.float32)}
            call = partial(session.run, None, feed)
            _report(f"onnx ({provider})", batch, measure(call, args.repeats, args.warmup, device))


def _torch_call(fn, x: torch.Tensor, dtype):
    def run():
        with torch.no_grad(), torch.autocast(x.device.type, dtype, enabled=dtype is not None):
            fn(x)

    return run


def _report(name: str, batch: int, times: list[float]) -> None:
    p50, p95 = np.median(times) / batch, percentile(times, 95) / batch
    print(
        f"  {name:<28} batch {batch:>3}: {p50 * 1e3:8.2f} ms/frame p50, {p95 * 1e3:8.2f} p95, "
        f"{1 / p50:8.1f} frames/s"
    )


if __name__ == "__main__":
    main()
