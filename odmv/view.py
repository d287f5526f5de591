"""One offline page of results: ``python -m odmv.view PATH [out=FILE.html]``.

PATH is a run folder (``outputs/train/<run>``, a demo's run), a report folder (``odmv.report``'s
``out``, ``experiments/results/mini``), a robustness report or a predict output folder. The page
is one self-contained HTML file (plotly.js inlined, nothing fetched: it opens offline in any
browser): the provenance read from the records; per scene every view's input fringe, the ground
truth, each prediction and its signed error with hover read-outs in mm (value, error, which
projectors light the pixel, shadowed), the error by height above the base plane, a 3D view of
each prediction against the ground truth coloured by error, and a row profile (a slider, or a
click on a map, picks the row); for reports the tables and their bar charts with every seed,
for robustness reports the MAE ratio against each shift's strength. Default ``out``:
``PATH/page.html`` (a predict or report folder's own page), never over an input.
"""

from __future__ import annotations

import sys
from pathlib import Path

from odmv.cli import run_app
from odmv.page.document import page_of


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if args else 2
    options = dict(a.split("=", 1) for a in args[1:] if "=" in a)
    unknown = [a for a in args[1:] if "=" not in a or not a.startswith("out=")]
    if unknown:
        print(f"error: {unknown[0]}: unknown; give PATH [out=FILE.html]", file=sys.stderr)
        return 2
    path = run_app(lambda: page_of(Path(args[0]), options.get("out")))
    size = path.stat().st_size / 1e6
    print(f"page: {path} ({size:.1f} MB; open it in a browser, offline)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
