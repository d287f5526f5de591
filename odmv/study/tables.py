"""The paper's three tables as the report lays them out, declared once: each row's label, what
it is (net, views, Table I row, base width) and the paper's figures. The view-count table and
Table I are ODMV-Net's own rows; Table II is the net registry's (conf/model/*.yaml with a
``table2`` entry) that a protocol lists in ``contenders``, plus the classical reference."""

from __future__ import annotations

from dataclasses import dataclass

from omegaconf import DictConfig

from odmv.config import compose_train, contenders
from odmv.models.odmvnet import TABLE_I


@dataclass(frozen=True)
class Row:
    table: str
    label: str
    model: str
    views: int
    ablation: str | None = None
    paper: tuple[float, float, float] | None = None  # MAE, MSE, RMSE as the paper prints them
    width: int | None = None  # a row of one base width; None: the runs no such row claims
    improvement_pct: float | None = None  # ODMV-Net's MAE reduction on this row, the paper's
    head: str = "depth"  # the paper's rows regress depth; head=phase runs are rows of their own
    capture: str | None = None  # a classical row on fewer images (reconstruct.Capture.key)


#: Table I's cumulative module rows (odmv.models.odmvnet.TABLE_I): key, label and the paper's
#: MAE, MSE, RMSE
ABLATION = tuple((row.key, row.label, row.paper) for row in TABLE_I)
PAPER_ODMV = ABLATION[-1][2]  # the full ODMV-Net at S = 4
VIEWS = ("S=1 (right)", "S=2 (right, up)", "S=3 (right, left, up)", "S=4 (all)")
#: the classical reference (odmv.study.classical) and its place among Table II's registry rows
CLASSICAL = Row("table2", "Classical phase shifting (4 projectors)", "classical", 4)
CLASSICAL_ORDER = 6
#: the classical method on the one image per projector a network sees (single-shot Fourier
#: transform profilometry, odmv.classical.reconstruct.CAPTURES[0]), just below the full
#: classical row
CLASSICAL_ONE = Row(
    "table2", "Classical, one image per projector (Fourier transform)", "classical", 4,
    capture="1x1",
)  # fmt: skip
TITLES = {
    "views": "View-count experiment (ODMV-Net, Sec. III.A)",
    "table1": "Table I: module ablation (ODMV-Net, S=4)",
    "table2": "Table II: model comparison",
}


def own_width(cfg: DictConfig) -> int | None:
    """The base width of a row that sets its own (ODMV-Net at width 24), None where the row
    trains the protocol's width for its net (``widths``)."""
    width = cfg.model.net.get("base_width")
    return width if width is not None and width != cfg.widths.get(cfg.model.name) else None


def table2(protocol: str | None = None) -> list[Row]:
    """Table II's rows for ``protocol`` (its ``contenders``; None: every registry row) in the
    registry's order, the classical reference in its place."""
    base = [f"experiment={protocol}"] if protocol else []
    names = compose_train(base).contenders if protocol else contenders("extra")
    keyed = [(CLASSICAL_ORDER, CLASSICAL), (CLASSICAL_ORDER + 0.5, CLASSICAL_ONE)]
    for name in names:
        cfg = compose_train([*base, f"model={name}"])
        entry = cfg.model.table2
        paper = entry.get("paper") or {}
        row = Row(
            "table2",
            entry.label,
            cfg.model.name,
            len(cfg.data.views),
            cfg.model.net.get("ablation"),
            tuple(paper[k] for k in ("mae_mm", "mse_mm2", "rmse_mm")) if paper else None,
            own_width(cfg),
            paper.get("improvement_pct"),
        )
        keyed.append((entry.order, row))
    return [row for _, row in sorted(keyed, key=lambda k: k[0])]


def tables(protocol: str | None = None) -> dict[str, list[Row]]:
    """The three tables in the paper's layout."""
    return {
        "views": [
            Row("views", label, "odmvnet", s, "multitask", PAPER_ODMV if s == 4 else None)
            for s, label in enumerate(VIEWS, 1)
        ],
        "table1": [Row("table1", label, "odmvnet", 4, key, p) for key, label, p in ABLATION],
        "table2": table2(protocol),
    }
