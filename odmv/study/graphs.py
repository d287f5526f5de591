"""Do a run's exported graphs keep its accuracy? Its float32 and int8 ONNX graphs (the files
``python -m odmv.export precisions=[float32,int8]`` writes) scored against the truth on the
checkpoint's test split, beside the checkpoint itself in PyTorch.

    python -m odmv.study graphs CKPT [CKPT ...] [--out DIR] [--calibration-scenes 16]
        [--int8-keep-float K]

Prints, per checkpoint: the MAE (mm) of PyTorch, of the float32 graph and of the int8 graph on
every valid test pixel, and the int8 graph's change against the float32 one (%). The graphs are
written into ``DIR/<run>/`` (default: a temporary folder).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import torch

from odmv.deploy.onnx import export_onnx
from odmv.deploy.quantize import export_precisions
from odmv.study.records import checkpoint_data
from odmv.training.checkpoint import CheckpointError
from odmv.training.metrics import DepthErrors
from odmv.training.module import net_input


def graph_maes(module, loader, graphs: dict[str, Path]) -> dict[str, float]:
    """MAE (mm) of the module and of each ONNX graph over ``loader``'s valid pixels."""
    import onnxruntime as ort

    sessions = {
        k: ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])
        for k, p in graphs.items()
    }
    errors = {k: DepthErrors() for k in ("pytorch", *sessions)}
    with torch.no_grad():
        for batch in loader:
            truth, valid = batch["depth_mm"], batch["valid"]
            errors["pytorch"].update(module.depth_mm(module.run(batch)), truth, valid)
            feed = {"inputs": net_input(batch).numpy()}
            if module.phase_head:
                feed["calibration"] = batch["calibration"].numpy()
            for k, session in sessions.items():
                pred = torch.from_numpy(session.run(None, feed)[0])
                errors[k].update(pred, truth, valid)
    return {k: float(e.compute()["mae_mm"]) for k, e in errors.items()}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+", metavar="CKPT")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--calibration-scenes", type=int, default=16)
    parser.add_argument(
        "--int8-keep-float", type=int, default=0, help="convolutions int8 leaves float32 (export)"
    )
    args = parser.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="odmv-graphs-"))
    print("| checkpoint | PyTorch MAE mm | float32 graph | int8 graph | int8 against float32 |")
    print("| --- | ---: | ---: | ---: | ---: |", flush=True)
    for path in args.checkpoints:
        print(  # the table stays on stdout alone; each row takes most of a minute on a CPU
            f"{path}: exporting float32 and int8 ({args.calibration_scenes} calibration scenes), "
            "then scoring PyTorch and both graphs on its test split ...",
            file=sys.stderr,
            flush=True,
        )
        try:
            module, dm = checkpoint_data(path, "test")
        except CheckpointError as e:
            raise SystemExit(f"error: {e}") from None
        folder = out / Path(path).resolve().parent.parent.name
        graph, _ = export_onnx(path, folder)
        scenes, keep = args.calibration_scenes, args.int8_keep_float
        int8 = export_precisions(path, graph, ["int8"], scenes, keep)["int8"][0]
        mae = graph_maes(module, dm.test_dataloader(), {"float32": graph, "int8": int8})
        change = 100 * (mae["int8"] / mae["float32"] - 1)
        print(
            f"| {path} | {mae['pytorch']:.4f} | {mae['float32']:.4f} | {mae['int8']:.4f} "
            f"| {change:+.1f} % |",
            flush=True,
        )
    return 0
