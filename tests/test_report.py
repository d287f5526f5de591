"""The report's verdicts on the paper's claims, from run metrics (no training needed)."""

import shutil
from pathlib import Path

import pytest
from helpers import compose_config

from odmv.study.report import (
    Run,
    _subset_cell,
    build_tables,
    claims_markdown,
    table_markdown,
    write_report,
)

SHADOWED = "S=4 (all) gains more over S=1 (right) on shadowed pixels"


def _run(model, views, mae, shadowed, seed, ablation=None):
    metrics = {
        "model": model,
        "views": ["right", "down", "left", "up"][:views],
        "seed": seed,
        "test/mae_mm": mae,
        "test/mae_mm_shadowed": shadowed,
    }
    if ablation:
        metrics["ablation"] = ablation
    # the held-out set agrees with the test split unless a test says otherwise
    metrics |= {f"heldout/{k[5:]}": v for k, v in metrics.items() if k.startswith("test/")}
    return Run(Path(f"{model}-{views}-{ablation}-{seed}"), metrics)


def _claims(runs):
    """claim -> verdict, from the claims table's rows."""
    rows = [line.strip("| ").split(" | ") for line in claims_markdown(build_tables(runs))]
    return {r[0]: r[-1] for r in rows if len(r) == 4}


def test_claims_get_verdicts_from_the_seed_spread():
    mae = {1: (0.30, 0.32), 2: (0.20, 0.21), 3: (0.25, 0.13), 4: (0.40, 0.41)}
    # shadowed: S = 4 loses 50 % against S = 1 there, 28-33 % on all pixels
    shadowed = {1: (0.60, 0.64), 2: (0.4, 0.4), 3: (0.4, 0.4), 4: (0.90, 0.96)}
    runs = [
        _run("odmvnet", s, mae[s][k], shadowed[s][k], k, "multitask") for s in mae for k in (0, 1)
    ]
    runs.append(_run("unet", 1, 0.5, 0.7, 0))  # one seed only
    claims = _claims(runs)
    assert claims["S=2 (right, up) below S=1 (right)"] == "holds"
    assert claims["S=3 (right, left, up) below S=2 (right, up)"].startswith("within seed noise")
    assert claims["S=4 (all) below S=3 (right, left, up)"] == "does not hold"
    assert claims["+RB&AG below Baseline (vanilla 3D U-Net)"] == "missing"
    assert claims["ODMV-Net (S=4) below UNet (S=1)"] == "one seed: no verdict"
    assert claims[SHADOWED] == "does not hold"
    # S = 4's shadowed errors halved: a 25 % gain there against the loss on all pixels
    for r in runs:
        if r.n_views == 4:
            r.metrics["test/mae_mm_shadowed"] /= 2
            r.metrics["heldout/mae_mm_shadowed"] /= 2
    assert _claims(runs)[SHADOWED] == "holds"


def test_first_unlit_claim_pairs_only_the_seeds_whose_records_have_the_metric():
    first = "S=4 (all) gains more over S=1 (right) on first-unlit pixels"
    runs = [_run("odmvnet", s, 0.3 - 0.02 * s, 0.6, k, "multitask") for s in (1, 4) for k in (0, 1)]
    assert _claims(runs)[first] == "missing"  # records from before the metric
    assert _claims(runs)[first.replace("unlit", "shadowed")] == "missing"
    # seeds 2 and 3 have it: four views halve the error where the one view has no fringe
    for k, (one, four) in zip((2, 3), ((0.8, 0.4), (0.9, 0.5)), strict=True):
        runs += [_run("odmvnet", s, 0.3 - 0.02 * s, 0.6, k, "multitask") for s in (1, 4)]
        for run, value in zip(runs[-2:], (one, four), strict=True):
            run.metrics["test/mae_mm_first_unlit"] = run.metrics["heldout/mae_mm_first_unlit"] = (
                value
            )
    assert _claims(runs)[first] == "holds"
    ours = next(c for c in build_tables(runs)["views"] if c.row.views == 4)
    assert _subset_cell(ours, "test/mae_mm_first_unlit") == "0.4500 ± 0.0707 (2 of 4 seeds)"
    # a gain on those pixels no larger than on all pixels (8 %) is no claim
    for r in runs:
        if r.n_views == 4 and "test/mae_mm_first_unlit" in r.metrics:
            r.metrics["test/mae_mm_first_unlit"] *= 2
            r.metrics["heldout/mae_mm_first_unlit"] *= 2
    assert _claims(runs)[first] == "does not hold"


def test_tables_give_each_seeds_thread_count_and_epochs_in_seed_order():
    runs = [_run("odmvnet", 4, 0.2, 0.5, k, "multitask") for k in (1, 0, 2)]
    runs[0].metrics["threads"] = 1  # seed 1
    runs[1].metrics["threads"] = 2  # seed 0; seed 2's record predates the field
    for r, epochs in zip(runs, (40, 70, 70), strict=True):
        r.metrics["epochs"] = epochs
    lines = table_markdown("views", build_tables(runs)["views"])
    head = lines[2].strip("| ").split(" | ")
    s4 = next(line for line in lines if line.startswith("| S=4")).strip("| ").split(" | ")
    s1 = next(line for line in lines if line.startswith("| S=1")).strip("| ").split(" | ")
    assert s4[head.index("threads")] == "2, 1, ? (differ)"  # two counts: not one configuration
    assert s4[head.index("epochs")] == "70, 40, 70"  # a row half retrained on a new schedule
    assert s1[head.index("threads")] == s1[head.index("epochs")] == "–"  # no run
    runs[0].metrics["threads"] = 2
    lines = table_markdown("views", build_tables(runs)["views"])
    s4 = next(line for line in lines if line.startswith("| S=4")).strip("| ").split(" | ")
    assert s4[head.index("threads")] == "2, 2, ?"


def test_runs_of_other_datasets_or_settings_are_rows_of_their_own_not_seeds():
    """Seeds of one row share a dataset and a setup; an Optuna trial at another learning rate
    and a run on another dataset beside them are their own rows, said in the labels, and the
    claims compare the setup on the dataset most runs used."""
    setup = {"optimizer.lr": "0.002", "model.net.base_width": "16"}
    runs = [_run("odmvnet", 4, 0.20 + 0.01 * k, 0.5, k, "multitask") for k in (0, 1)]
    runs += [_run("odmvnet", 4, mae, mae, 0, "multitask") for mae in (0.9, 3.0)]
    runs += [_run("odmvnet", 3, 0.3, 0.8, k, "multitask") for k in (0, 1)]
    for r in runs:
        r.metrics |= {"dataset": "data/synthetic-a", "dataset_sha1": "aaa", "setup": setup}
    runs[2].metrics["setup"] = setup | {"optimizer.lr": "0.0003"}  # a trial of a search
    runs[3].metrics |= {"dataset": "data/synthetic-b", "dataset_sha1": "bbb"}  # the quickstart's
    views = build_tables(runs)["views"]
    s4 = [c for c in views if c.row.label == "S=4 (all)"]
    assert [(c.label, len(c.runs), c.primary) for c in s4] == [
        ("S=4 (all) [dataset synthetic-a; optimizer.lr=0.002]", 2, True),
        ("S=4 (all) [dataset synthetic-a; optimizer.lr=0.0003]", 1, False),
        ("S=4 (all) [dataset synthetic-b; optimizer.lr=0.002]", 1, False),
    ]
    assert s4[0].stat("test/mae_mm")[0] == pytest.approx(0.205)  # not 1.0775 over four
    lines = table_markdown("views", views)
    assert any(line.startswith(f"| {s4[1].label} | 1 | 0.9000 |") for line in lines)
    claims = _claims(runs)
    assert f"{s4[0].label} below S=3 (right, left, up)" in claims
    assert not any("0.0003" in claim or "synthetic-b" in claim for claim in claims)
    # records from before setups were recorded: grouped by dataset alone
    for r in runs:
        del r.metrics["setup"]
    s4 = [c for c in build_tables(runs)["views"] if c.row.label == "S=4 (all)"]
    assert [(c.label, len(c.runs)) for c in s4] == [
        ("S=4 (all) [dataset synthetic-a]", 3),
        ("S=4 (all) [dataset synthetic-b]", 1),
    ]


def test_a_run_at_a_rows_own_width_goes_to_that_row_only():
    runs = [_run("odmvnet", 4, 0.20 + 0.01 * k, 0.5, k, "multitask") for k in (0, 1)]
    runs += [_run("odmvnet", 4, 0.10 + 0.01 * k, 0.4, k, "multitask") for k in (0, 1)]
    for r, width in zip(runs, (16, 16, 24, 24), strict=True):
        r.metrics["width"] = width
    tables = build_tables(runs)
    by_label = {c.row.label: c for c in tables["table2"]}
    assert [r.width for r in by_label["ODMV-Net (S=4)"].runs] == [16, 16]
    assert [r.width for r in by_label["ODMV-Net at UHRNet's size (S=4, width 24)"].runs] == [24, 24]
    assert all(r.width == 16 for c in tables["views"] + tables["table1"] for r in c.runs)
    assert by_label["ODMV-Net (S=4)"].stat("test/mae_mm")[0] == pytest.approx(0.205)


def test_a_claim_holds_only_where_the_test_split_and_the_held_out_set_both_say_so():
    two = "S=2 (right, up) below S=1 (right)"
    mae = {1: (0.30, 0.32), 2: (0.20, 0.21)}
    runs = [_run("odmvnet", s, mae[s][k], 0.5, k, "multitask") for s in mae for k in (0, 1)]
    assert _claims(runs)[two] == "holds"
    for r in runs:  # on 200 fresh scenes S = 2 is the worse
        r.metrics["heldout/mae_mm"] = {1: 0.25, 2: 0.35}[r.n_views] + 0.01 * r.metrics["seed"]
    assert _claims(runs)[two] == "test split: holds; held-out: does not hold"
    for r in runs:  # records from before held-out scoring
        r.metrics = {k: v for k, v in r.metrics.items() if not k.startswith("heldout/")}
    assert _claims(runs)[two] == "test split: holds; held-out: missing"
    # the held-out columns say where a row has no held-out scores
    lines = table_markdown("views", build_tables(runs)["views"])
    head = lines[2].strip("| ").split(" | ")
    s2 = next(line for line in lines if line.startswith("| S=2")).strip("| ").split(" | ")
    assert s2[head.index("held-out MAE (mm)")] == "–"


def test_the_committed_mini_report_rebuilds_from_its_records_byte_for_byte(tmp_path):
    # python -m odmv.report runs=[experiments/results/mini/runs] out=experiments/results/mini
    # protocol=mini: what the repository says of its main result is what its records say
    results = Path(__file__).resolve().parents[1] / "experiments" / "results" / "mini"
    write_report([results / "runs"], tmp_path, protocol="mini")
    assert (tmp_path / "tables.md").read_text() == (results / "tables.md").read_text()


def test_a_report_without_protocol_takes_it_from_the_records(tmp_path, monkeypatch):
    """Run from another folder, the committed records name their preset (resumed runs and the
    classical row, which do not, aside)."""
    results = Path(__file__).resolve().parents[1] / "experiments" / "results" / "mini"
    monkeypatch.chdir(tmp_path)
    write_report([results / "runs"], tmp_path / "report")
    header = (tmp_path / "report" / "tables.md").read_text().splitlines()[:4]
    assert "- protocol: mini (from the runs' records)" in header


def test_odmvnet_at_another_width_is_judged_against_the_baseline_of_its_size():
    mae = {("odmvnet", 16): 0.2, ("odmvnet", 24): 0.1, ("uhrnet", None): 0.15, ("hnet", None): 0.3}
    size = {16: 13.8e6, 24: 31.0e6, "uhrnet": 30.3e6, "hnet": 8.6e6}
    runs = []
    for (model, width), m in mae.items():
        for k in (0, 1):
            r = _run(model, 4 if model == "odmvnet" else 1, m + 0.01 * k, 0.5, k, "multitask")
            r.metrics |= {"width": width, "parameters": size[width or model]}
            runs.append(r)
    w24 = "ODMV-Net at UHRNet's size (S=4, width 24) below"
    claims = _claims(runs)
    assert claims[f"{w24} UHRNet (S=1)"] == "holds"
    assert [c for c in claims if c.startswith(w24)] == [f"{w24} UHRNet (S=1)"]
    for r in runs:  # records without sizes: no peer, no claim
        r.metrics.pop("parameters")
    assert not any(c.startswith(w24) for c in _claims(runs))


def test_a_demo_run_with_its_evaluation_folder_is_one_run(trained, tmp_path):
    """The demo writes outputs/demo/<time>/ (the run) and its evaluation/ (odmv.evaluate's
    metrics of the same checkpoint): the report takes the run and passes over the evaluation."""
    from odmv.study.results import find_runs
    from odmv.training.evaluation import evaluate

    run = shutil.copytree(trained[0], tmp_path / "demo" / "2026-12-06_08-00-00")
    ckpt = run / "checkpoints" / Path(trained[1]["best_checkpoint"]).name
    cfg = compose_config(
        "evaluate",
        [f"ckpt_path={ckpt}", f"paths.output_dir={run / 'evaluation'}", "figures=0"],
    )
    evaluate(cfg)
    runs, pending = find_runs([tmp_path / "demo"])
    assert [r.folder for r in runs] == [run] and pending == []
