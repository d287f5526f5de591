"""A dataset's rig as a calibration file: ``python -m odmv.calibration DATASET rig.yaml``.

Writes the OpenCV-style calibration that odmv reads from a real rig (odmv/io/calibration.py's
schema) for the rig of ``DATASET``'s manifest at its stored image size: the twin's, to rehearse
the own-rig path on it (captures -> convert -> adapt -> predict, docs/dataset.md), or one a
dataset was converted with, to give it to another tool. An existing file is never replaced.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import yaml

from odmv.cli import run_app
from odmv.io.atomic import write_text
from odmv.io.calibration import calibration_of, parse_calibration
from odmv.io.guard import refuse_inside
from odmv.io.manifest import load_manifest


def write_calibration(dataset: Path, out: Path) -> str:
    """Write the calibration file of ``dataset``'s rig to ``out``; returns what it holds."""
    m = load_manifest(dataset)
    if m.rig is None:
        raise ValueError(f"{dataset}: its manifest has no rig calibration (an import without one)")
    refuse_inside("out", [out], [], protected=[dataset])
    if out.exists():
        raise FileExistsError(f"{out}: exists; a calibration file is never replaced")
    content = calibration_of(m.rig, m.width_px, m.height_px)
    parse_calibration(content, out)  # what a reader gets back, checked before it is written
    write_text(out, yaml.safe_dump(content, sort_keys=False, default_flow_style=None))
    return f"camera {m.width_px}x{m.height_px} px, projectors {', '.join(content['projectors'])}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m odmv.calibration", description=__doc__.splitlines()[0]
    )
    ap.add_argument("dataset", type=Path, help="dataset folder (holds manifest.json)")
    ap.add_argument("out", type=Path, help="the calibration file to write (.yaml or .json)")
    args = ap.parse_args(argv)
    what = run_app(lambda: write_calibration(args.dataset, args.out))
    print(f"{args.out}: the rig of {args.dataset} ({what})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
