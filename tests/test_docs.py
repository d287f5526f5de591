"""Figures the docs quote about the presets, checked against the configs they describe, so the
two cannot drift apart again."""

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
