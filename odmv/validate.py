"""Check a dataset folder against the contract: ``python -m odmv.validate PATH [--quick]``.

Prints every problem on its own line (file named) and exits 1, or prints a one-line summary and
exits 0. Nothing on disk is modified.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from odmv.io.validation import validate


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m odmv.validate", description=__doc__.splitlines()[0]
    )
    ap.add_argument("path", type=Path, help="dataset folder (holds manifest.json)")
    ap.add_argument("--quick", action="store_true", help="check headers only, skip pixel values")
    args = ap.parse_args(argv)
    report = validate(args.path, deep=not args.quick)
    if report.ok:
        print(report.summary(args.path))
        return 0
    for line in report.problems:
        print(line)
    print(f"{args.path}: {len(report.problems)} problem(s)", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
