"""python -m odmv.study: one command for the analysis verbs, each with its own --help."""

from pathlib import Path

import pytest
from helpers import compose_config, tiny_overrides

from odmv.study import VERBS
from odmv.study.__main__ import main


def test_help_lists_every_verb_with_what_it_does(capsys):
    assert main(["--help"]) == 0
    out = capsys.readouterr().out
    for verb in VERBS:
        line = next(line for line in out.splitlines() if line.strip().startswith(verb + " "))
        assert len(line.split(maxsplit=1)[1]) > 20  # its docstring's first paragraph
    assert main([]) == 2  # no verb: the usage, and a failing status


@pytest.mark.parametrize("verb", sorted(VERBS))
def test_each_verb_tells_its_arguments(verb, capsys):
    with pytest.raises(SystemExit) as done:
        main([verb, "--help"])
    assert done.value.code == 0
    assert f"usage: python -m odmv.study {verb}" in capsys.readouterr().out


def test_an_unknown_verb_is_one_line_naming_the_verbs(capsys):
    assert main(["nope"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: 'nope' is no verb of odmv.study") and "summarize" in err


def test_robustness_scores_runs_and_the_classical_method_on_shifted_twins(trained, tmp_path):
    from odmv.io.manifest import load_manifest
    from odmv.sim.shifts import Shift
    from odmv.study import robustness

    run, metrics = trained
    source = Path(metrics["dataset"])
    shifts = [Shift("gamma", 2.2), Shift("dead_view", "down")]
    scores = robustness.score_run(run, shifts, scenes=3, threads=1)
    assert list(scores) == ["nominal", "gamma:2.2", "dead_view:down"]
    assert all(s["scenes"] == 3 and s["test/mae_mm"] > 0 for s in scores.values())
    data = Path(scores["gamma:2.2"]["dataset"])
    m = load_manifest(data)
    # the twin's scenes (seed + 2), the nominal calibration, the shift recorded
    nominal = load_manifest(source)
    assert m.extra["simulation"]["seed"] == nominal.extra["simulation"]["seed"] + 2
    assert m.rig == nominal.rig
    assert m.extra["simulation"]["shift"]["name"] == "gamma"
    stamp = (run / "robustness.json").stat().st_mtime_ns
    assert robustness.score_run(run, shifts[:1], scenes=3) == {
        k: scores[k] for k in ("nominal", "gamma:2.2", "dead_view:down")
    }
    assert (run / "robustness.json").stat().st_mtime_ns == stamp  # nothing scored again
    classical = robustness.score_classical(source, shifts, scenes=3)
    # 12-step phase shifting cancels the gamma harmonics below the 12th: gamma barely moves it
    assert abs(classical["gamma:2.2"]["test/mae_mm"] - classical["nominal"]["test/mae_mm"]) < 0.05
    rows = {"odmvnet S=4": [scores], "classical": [classical]}
    md = robustness.write_tables(rows, shifts, tmp_path).read_text()
    ratio = scores["gamma:2.2"]["test/mae_mm"] / scores["nominal"]["test/mae_mm"]
    assert f"{scores['gamma:2.2']['test/mae_mm']:.3f} ({ratio:.2f}x)" in md
    assert "% covered" in md and (tmp_path / "robustness.png").is_file()
    assert len((tmp_path / "robustness.csv").read_text().splitlines()) == 1 + 2 * 3


def test_datasets_that_differ_only_in_training_scenes_share_one_twin(
    tiny_dataset, tmp_path, capsys
):
    """The held-out and shifted twins of a randomized or shifted training set are the nominal
    set's twins: one folder, rendered once; another scene seed is another twin."""
    import json

    from odmv.io.manifest import MANIFEST
    from odmv.sim.shifts import Shift
    from odmv.study.heldout import heldout_dataset
    from odmv.study.robustness import shifted_set

    manifest = json.loads((tiny_dataset / MANIFEST).read_text())
    sources = {}
    for name, extra in (
        ("nominal", {}),
        ("randomized", {"randomize": {"gamma": [1.0, 2.2]}}),
        ("shifted", {"shift": Shift("defocus", 1.5).to_dict()}),
        ("other_seed", {"seed": manifest["simulation"]["seed"] + 5}),
    ):
        m = manifest | {"simulation": manifest["simulation"] | extra}
        (tmp_path / name).mkdir()
        (tmp_path / name / MANIFEST).write_text(json.dumps(m))
        sources[name] = tmp_path / name
    held = heldout_dataset(sources["nominal"], scenes=2)
    assert "rendering" in capsys.readouterr().out
    assert heldout_dataset(sources["randomized"], scenes=2) == held
    assert heldout_dataset(sources["shifted"], scenes=2) == held
    assert "rendering" not in capsys.readouterr().out
    assert heldout_dataset(sources["other_seed"], scenes=2) != held
    gamma = Shift("gamma", 2.2)
    assert shifted_set(sources["randomized"], gamma, 2) == shifted_set(sources["nominal"], gamma, 2)
    assert shifted_set(sources["nominal"], gamma, 2) not in (
        held,
        shifted_set(sources["nominal"], Shift("gamma", 1.5), 2),
    )
    assert json.loads((held / MANIFEST).read_text())["simulation"].get("randomize") is None
    # without the classical method: the networks' images only, unless a full set is there
    noise = Shift("noise", 2.0)
    net_only = shifted_set(sources["nominal"], noise, 2, classical=False)
    assert json.loads((net_only / MANIFEST).read_text())["images"] == "training"
    full = shifted_set(sources["nominal"], noise, 2)
    assert full != net_only and json.loads((full / MANIFEST).read_text())["images"] == "full"
    assert shifted_set(sources["nominal"], noise, 2, classical=False) == full


def test_robustness_rows_keep_randomized_and_dropout_trainings_apart(trained, tmp_path):
    """A net trained on the randomized twin or with view dropout is a row of its own, not a
    further seed of the nominal net."""
    import json

    from omegaconf import OmegaConf

    from odmv.study import robustness

    run, metrics = trained
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    labels = []
    for name, randomize, dropout, init in (
        ("a", None, None, None),
        ("b", "all", None, None),
        ("c", None, 0.25, None),
        ("d", None, 0.25, str(run)),
    ):
        folder = tmp_path / name
        (folder / ".hydra").mkdir(parents=True)
        OmegaConf.update(cfg, "data.randomize", randomize, force_add=True)
        OmegaConf.update(cfg, "view_dropout", dropout, force_add=True)
        OmegaConf.update(cfg, "init_from", init, force_add=True)
        OmegaConf.save(cfg, folder / ".hydra" / "config.yaml")
        labels.append(robustness._label(folder, json.loads((run / "metrics.json").read_text())))
    assert labels[0] == robustness._label(run, metrics)
    assert labels[1] == labels[0] + ", randomize=all"
    assert labels[2] == labels[0] + ", view_dropout=0.25"
    assert labels[3] == labels[2] + ", fine-tuned"


def test_robustness_declares_views_missing_to_a_view_dropout_net(trained, tiny_dataset, tmp_path):
    """A net trained with view dropout is scored with each view declared missing; the report
    puts it beside the same net without dropout and the three-view net, under the view that
    one lacks. A net trained without dropout is never told a view is missing."""
    from csv import DictReader

    from odmv.sim.shifts import Shift
    from odmv.study import robustness
    from odmv.training.run import train

    base_run, _ = trained
    run = tmp_path / "dropout"
    extra = ["view_dropout=0.5", "views=4", "reference=true"]
    train(compose_config("train", tiny_overrides(tiny_dataset, run, *extra)))
    shifts = [Shift("dead_view", "down")]
    scores = robustness.score_run(run, shifts, scenes=3, threads=1, missing=("down", "up"))
    assert list(scores) == ["nominal", "dead_view:down", "missing:down", "missing:up"]
    declared, dark = scores["missing:down"]["test/mae_mm"], scores["dead_view:down"]["test/mae_mm"]
    assert declared > 0 and declared != scores["nominal"]["test/mae_mm"] and declared != dark
    assert scores["missing:down"]["dataset"] == scores["nominal"]["dataset"]  # the nominal twin
    base = robustness.score_run(base_run, shifts, scenes=3, threads=1, missing=("down",))
    assert "missing:down" not in base
    three = {"nominal": {"test/mae_mm": 0.5}}  # a three-view net's score, for the table
    rows = {
        "odmvnet S=4": [base],
        "odmvnet S=4, view_dropout=0.5": [scores],
        "odmvnet S=3": [three],
    }
    views = {"odmvnet S=3": ["right", "left", "up"]}
    md = robustness.write_tables(rows, shifts, tmp_path / "report", views).read_text()
    table = md.split("## Any set of working projectors")[1]
    lines = {
        line.split(" | ")[0][2:]: line for line in table.splitlines() if line.startswith("| odmv")
    }
    cells = lines["odmvnet S=4, view_dropout=0.5"].split(" | ")[2:7]  # all, missing r d l u
    assert cells == [f"{scores['nominal']['test/mae_mm']:.3f}", "–", f"{declared:.3f}", "–",
                     f"{scores['missing:up']['test/mae_mm']:.3f}"]  # fmt: skip
    assert lines["odmvnet S=3"].split(" | ")[2:5] == ["–", "–", "0.500"]  # under `down`
    assert "against 0.5000 mm for odmvnet S=3" in table
    csv = (tmp_path / "report" / "robustness.csv").read_text()
    assert "missing:up" in csv and "missing:up" not in md.split("## Any set")[0]
    sets = {(r["model"], r["set"]) for r in DictReader(csv.splitlines())}
    assert ("odmvnet S=4, view_dropout=0.5", "missing:up") in sets
    assert ("odmvnet S=4", "missing:up") not in sets  # never told a view is missing: no row


def test_the_robustness_study_says_its_cost_before_it_starts(tiny_dataset):
    from odmv.sim.shifts import parse_shift
    from odmv.study.robustness import plan

    line = plan(tiny_dataset, [parse_shift("noise:2"), parse_shift("gloss:0.5")], 100, 2, True)
    assert line.startswith("robustness: 3 sets of 100 scenes at 64x64 px (the nominal twin and 2")
    assert "each scored with 2 run(s) and the classical method" in line
    assert " MB;" in line or " GB;" in line
    cheap = plan(tiny_dataset, [parse_shift("noise:2")], 100, 1, False)
    assert "the networks' images only" in cheap


def test_a_classical_curve_far_off_the_nets_does_not_set_their_scale():
    """The robustness figures keep the nets readable where the classical method moves 6x and
    they 1.03x: its curve runs off the top with its peak written; where all fit, no change."""
    from odmv.study.robustness import nets_scale, off_scale_note

    curves = {"ODMV-Net (S=4)": ([0, 0.1], [1.0, 1.03]), "UHRNet (S=1)": ([0, 0.1], [1.0, 0.99]),
              "classical (nominal calibration)": ([0, 0.1], [1.0, 6.36])}  # fmt: skip
    lo, hi, others = nets_scale(curves)
    assert lo < 0.99 and 1.03 < hi < 1.2 and others == {"classical (nominal calibration)": 6.36}
    assert off_scale_note(others) == "classical up to 6.4x, off scale"
    curves["classical (nominal calibration)"] = ([0, 0.1], [1.0, 1.1])
    assert nets_scale(curves) is None
