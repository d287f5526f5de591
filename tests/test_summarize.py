import shutil

import pytest

from odmv.study import summarize


def test_summarize_scores_a_run_and_a_record_that_kept_only_its_metrics(trained, tmp_path, capsys):
    run, metrics = trained
    record = tmp_path / "record"  # a committed reproduction record: metrics.json alone
    record.mkdir()
    shutil.copy(run / "metrics.json", record / "metrics.json")
    (record / "heldout.json").write_text('{"test/mae_mm": 0.123}')  # its held-out score
    assert summarize.main([f"run={run}", f"record={record}"]) == 0
    rows = {
        r.split("|")[1].strip(): r.split("|")[2:-1] for r in capsys.readouterr().out.splitlines()
    }
    mae = f"{metrics['test/mae_mm']:.3f}"
    assert [c.strip() for c in rows["run"][:2]] == ["1", mae]
    assert [c.strip() for c in rows["record"][:2]] == ["1", mae]
    interior = f"{metrics['test/mae_mm_interior']:.3f}"
    assert [c.strip() for c in rows["run"][4:6]] == [interior, f"{metrics['test/mae_mm_edge']:.3f}"]
    assert rows["record"][6].strip() == "0.123" and rows["run"][6].strip() == "–"
    # the record has no per-scene file: no family figures and no worst scene
    assert [c.strip() for c in rows["record"][8:]] == ["–"] * 4
    assert "–" not in rows["run"][-1]  # the run names its worst scene
    with pytest.raises(ValueError, match="none=.*: no run folder matches"):  # not a 0-run row
        summarize.main([f"none={tmp_path}/missing*"])
