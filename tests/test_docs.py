"""Figures the docs quote, checked against what they describe so the two cannot drift apart: the
presets' settings against the configs, the findings' results against the committed records."""

import csv
import json
import re
from pathlib import Path

import pytest
from helpers import compose_config

ROOT = Path(__file__).resolve().parent.parent


def preset(*overrides) -> dict:
    cfg = compose_config("train", list(overrides))
    return {
        "px": cfg.data.resolution,
        "batch": cfg.data.batch_size,
        "epochs": cfg.trainer.max_epochs,
        "width": cfg.widths.odmvnet,
        "scenes": cfg.data.simulate.scenes,
    }


PAPER, MINI, QUICK = (), ("experiment=mini",), ("experiment=quickstart",)
CASES = [  # doc, quoted text (numbers as groups), the settings they must equal
    ("docs/training.md", r"the paper protocol \((\d+) px, batch (\d+), (\d+) epochs\)",
     [(PAPER, "px"), (PAPER, "batch"), (PAPER, "epochs")]),
    ("docs/training.md", r"(\d+) px, (\d+) epochs on the (\d+)-scene synthetic default",
     [(PAPER, "px"), (PAPER, "epochs"), (PAPER, "scenes")]),
    ("docs/reproduce.md", r"\| ODMV-Net width \| (\d+) \(113\.7 M\) \| (\d+) \(",
     [(PAPER, "width"), (MINI, "width")]),
    ("conf/experiment/quickstart.yaml", r"at width (\d+);", [(QUICK, "width")]),
]  # fmt: skip


@pytest.mark.parametrize("doc, pattern, keys", CASES)
def test_quoted_preset_figures_match_the_configs(doc, pattern, keys):
    text = " ".join((ROOT / doc).read_text().replace("#", " ").split())
    found = re.search(pattern, text)
    assert found, f"{doc}: no text matching {pattern!r}"
    quoted = [int(v) for v in found.groups()]
    assert quoted == [preset(*overrides)[key] for overrides, key in keys], doc


def _recorded_numbers() -> list[float]:
    """The figures findings.md may quote: the MAEs of the reports' run lists, and every number
    of the reports and the lab notebook."""
    results = ROOT / "experiments" / "results"
    found = []
    for runs in results.rglob("runs.csv"):
        for row in csv.DictReader(runs.open()):
            found += [float(v) for k, v in row.items() if "mae" in k and v]
    docs = ("mini/tables.md", "robustness/robustness.md", "accuracy/notebook.md")
    docs += ("adapt/adapt.md", "adapt/notebook.md")
    for doc in docs:
        found += [float(x) for x in re.findall(r"\d+\.\d+", (results / doc).read_text())]
    for record in results.glob("**/runs/*/*.json"):
        found += _maes(json.loads(record.read_text()))
    return found


def _maes(tree) -> list[float]:
    """The MAE values of a record (metrics by name, nested per shift in robustness.json and
    per move in prior.json)."""
    if isinstance(tree, list):
        return [x for v in tree for x in _maes(v)]
    if not isinstance(tree, dict):
        return []
    found = [v for k, v in tree.items() if "mae" in k and isinstance(v, float)]
    return found + [x for v in tree.values() for x in _maes(v)]


def test_findings_quote_recorded_figures():
    """docs/findings.md quotes MAEs at the report's precision (4 decimals) and ratios to the
    nominal MAE (N.NNx); each must be a figure of the committed records, so the page cannot
    drift from the results it summarizes."""
    text = (ROOT / "docs" / "findings.md").read_text()
    recorded = _recorded_numbers()
    quoted = re.findall(r"(?<![\d.])(\d+\.\d{4})(?!\d)", text)
    quoted += re.findall(r"(?<![\d.])(\d+\.\d{2})x", text)
    assert len(quoted) > 40, "findings.md should quote its figures"
    missing = [
        q for q in quoted
        if not any(round(v, len(q.split(".")[1])) == float(q) for v in recorded)
    ]  # fmt: skip
    assert not missing, f"docs/findings.md quotes figures no record holds: {missing}"
