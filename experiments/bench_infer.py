"""Inference latency of a preset's net: per frame (p50, p95) and frames/s, at batch 1 and a
larger batch, for PyTorch eager, torch.compile and ONNX Runtime (the graph odmv.export writes).

    python experiments/bench_infer.py --preset paper --model odmvnet        # 480 px, 4 views
    python experiments/bench_infer.py --preset paper --device cuda --precision bf16 --batches 1 8
    python experiments/bench_infer.py --preset quickstart --runtimes eager onnx

The deployment table (docs/deploy.md): ONNX Runtime at batch 1 for several nets, sizes and
graph precisions, each cell in a fresh process that imports ONNX Runtime alone (its peak
resident memory is what a consumer of the graph needs):

    python experiments/bench_infer.py --preset mini --table --models odmvnet odmvnet_lite \
        --sizes 64 128 256 480 --onnx-precisions float32 int8 --set head=phase

A frame is one set of S view images in, one depth map (mm) out. Weights are random: latency
does not depend on them (int8 is calibrated on random inputs of the same shape). ONNX Runtime
uses CUDA when --device cuda and it is available.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from functools import partial
from pathlib import Path

import numpy as np
import torch

from odmv.classical.geometry import triangulation_maps
from odmv.cli import quiet_lightning
from odmv.deploy.onnx import DepthInMM, export_graph
from odmv.io.manifest import FringeSpec
from odmv.rig import Rig
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


def _onnx_session(model: torch.nn.Module, example: tuple, device: torch.device):
    import onnx
    import onnxruntime as ort

    path = Path(tempfile.mkdtemp(prefix="odmv-bench-")) / "model.onnx"
    onnx.save(export_graph(model.cpu(), *example), path)
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
    ap.add_argument("--table", action="store_true", help="the deployment table (ONNX Runtime)")
    ap.add_argument("--models", nargs="+", default=["odmvnet"], help="--table: the nets")
    ap.add_argument("--sizes", type=int, nargs="+", default=[480], help="--table: image px")
    ap.add_argument("--onnx-precisions", nargs="+", default=["float32"], help="float32, int8")
    args = ap.parse_args()
    quiet_lightning()  # the deprecation notes Lightning and torch.export raise
    if args.table:
        return _table(args)

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
    example = _example(module, cfg, 2)
    if "eager" in args.runtimes:
        runners["eager"] = model
    if "compiled" in args.runtimes:
        runners["compiled"] = torch.compile(model, mode="max-autotune-no-cudagraphs")
    session = provider = None
    if "onnx" in args.runtimes:
        session, provider = _onnx_session(model, example, device)
    for batch in args.batches:
        x, maps = _example(module, cfg, batch)
        args_on = [t.to(device) for t in (x, maps) if t is not None]
        for name, fn in runners.items():
            run = _torch_call(fn, args_on, dtype)
            _report(name, batch, measure(run, args.repeats, args.warmup, device))
        if session is not None:
            feed = {"inputs": x.numpy()} | ({} if maps is None else {"calibration": maps.numpy()})
            call = partial(session.run, None, feed)
            _report(f"onnx ({provider})", batch, measure(call, args.repeats, args.warmup, device))


def _example(module, cfg, batch: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """A synthetic input of the preset's shape, and calibration maps for a phase-head net (the
    twin's rig at the finest fringe: any rig's maps are valid input)."""
    x = net_input(synthetic_batch(cfg, batch, torch.device("cpu")))
    if not module.phase_head:
        return x, None
    h, w = input_size(cfg)
    maps = triangulation_maps(Rig(), list(cfg.data.views), h, w, FringeSpec().periods_px[-1])
    return x, torch.from_numpy(maps)[None].expand(batch, *maps.shape).contiguous()


def _table(args) -> None:
    """One ONNX Runtime row per net, size and precision (batch 1), as a Markdown table."""
    import onnx

    from odmv.deploy.quantize import int8_model

    print("| net | parameters | input | graph | p50 ms | p95 ms | frames/s | peak RSS |")
    print("| --- | ---: | --- | --- | ---: | ---: | ---: | ---: |")
    tmp = Path(tempfile.mkdtemp(prefix="odmv-bench-"))
    for model_name in args.models:
        for size in args.sizes:
            cfg = preset_config(args.preset, model_name, [*args.set, f"data.resolution={size}"])
            module = build_module(cfg).eval()
            params = sum(p.numel() for p in module.net.parameters())
            x, maps = _example(module, cfg, 1)
            path = tmp / f"{model_name}-{size}.onnx"
            onnx.save(export_graph(DepthInMM(module).eval(), x, maps), path)
            feed = {"inputs": x.numpy()} | ({} if maps is None else {"calibration": maps.numpy()})
            np.savez(path.with_suffix(".npz"), **feed)
            graphs = {"float32": path}
            if "int8" in args.onnx_precisions:
                rngs = [np.random.default_rng(i) for i in range(4)]  # random: timing only
                shape = feed["inputs"].shape
                calibration = [
                    feed | {"inputs": r.uniform(-1, 1, shape).astype(np.float32)} for r in rngs
                ]
                graphs["int8"] = path.with_name(f"{path.stem}.int8.onnx")
                onnx.save(int8_model(path, calibration), graphs["int8"])
            for precision in args.onnx_precisions:
                cell = [sys.executable, "-c", ORT_CELL, str(graphs[precision])]
                cell += [str(path.with_suffix(".npz")), str(args.repeats), str(args.warmup)]
                done = subprocess.run(cell, capture_output=True, text=True)
                row = f"| {model_name} | {params / 1e6:.2f} M | {len(cfg.data.views)} x {size} px "
                if done.returncode:  # a graph ONNX Runtime refuses: its last line, the table on
                    print(f"{row}| {precision} | failed: {done.stderr.strip().splitlines()[-1]} |")
                    continue
                got = json.loads(done.stdout)
                p50, p95 = np.median(got["seconds"]), percentile(got["seconds"], 95)
                print(
                    f"{row}| {precision} | {p50 * 1e3:.1f} | {p95 * 1e3:.1f} | {1 / p50:.1f} "
                    f"| {got['peak_rss_mib']:.0f} MiB |",
                    flush=True,
                )


#: one table cell: a process of ONNX Runtime and numpy alone (no torch), so its peak resident
#: memory is what a consumer of the graph needs; argv: graph, input (.npz), repeats, warmup
ORT_CELL = """
import json, sys, time
import numpy as np, onnxruntime as ort
path, inputs, repeats, warmup = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])
with np.load(inputs) as z:
    feed = {k: z[k] for k in z.files}
session = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
for _ in range(warmup):
    session.run(None, feed)
seconds = []
for _ in range(repeats):
    t0 = time.perf_counter()
    session.run(None, feed)
    seconds.append(time.perf_counter() - t0)
# VmHWM: this process image's peak (ru_maxrss would keep the forking parent's across exec)
status = open("/proc/self/status").read().split("VmHWM:")[1]
rss = int(status.split()[0]) / 1024
print(json.dumps({"seconds": seconds, "peak_rss_mib": rss}))
"""


def _torch_call(fn, inputs: list[torch.Tensor], dtype):
    device = inputs[0].device.type

    def run():
        with torch.no_grad(), torch.autocast(device, dtype, enabled=dtype is not None):
            fn(*inputs)

    return run


def _report(name: str, batch: int, times: list[float]) -> None:
    p50, p95 = np.median(times) / batch, percentile(times, 95) / batch
    print(
        f"  {name:<28} batch {batch:>3}: {p50 * 1e3:8.2f} ms/frame p50, {p95 * 1e3:8.2f} p95, "
        f"{1 / p50:8.1f} frames/s"
    )


if __name__ == "__main__":
    main()
