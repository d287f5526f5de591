"""Result pages (python -m odmv.view): what they hold, written from real run, report,
robustness and predict folders, and how a browser shows them (headless Chromium)."""

import csv
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from odmv.deploy.predict import predict
from odmv.io.runfolder import PREDICTIONS
from odmv.page.document import markdown_html, page_of
from odmv.page.plots import signed_log
from odmv.page.sources import PageError, read

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
#: put at the top of the page under test: records script errors and every resource the page
#: loads, and writes them into <body> once the page's own script has run
PROBE = """<script>
window.__errors = [];
window.addEventListener('error',
  e => window.__errors.push(String(e.message || e.target.src)), true);
window.addEventListener('load', () => setTimeout(() => {
  const b = document.body;
  b.dataset.errors = JSON.stringify(window.__errors);
  b.dataset.requests = JSON.stringify(performance.getEntriesByType('resource').map(r => r.name));
  b.dataset.drawn = String(document.querySelectorAll('.js-plotly-plot').length);
}, 500));
</script>"""


def _browser(page: Path, tmp_path: Path) -> tuple[dict, Image.Image]:
    """Open ``page`` (with PROBE) in headless Chromium, every network request refused:
    (what PROBE recorded, a screenshot)."""
    probed = tmp_path / "probed.html"
    probed.write_text(page.read_text().replace("<head>", "<head>" + PROBE, 1))
    args = [
        CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
        "--proxy-server=127.0.0.1:9", "--host-resolver-rules=MAP * ~NOTFOUND",
        "--virtual-time-budget=20000", "--window-size=1400,1800",
    ]  # fmt: skip
    dom = subprocess.run(
        [*args, "--dump-dom", probed.as_uri()], capture_output=True, text=True, timeout=180
    ).stdout
    body = re.search(r"<body([^>]*)>", dom)
    assert body, f"no page rendered: {dom[:300]}"
    found = dict(re.findall(r'data-(\w+)="([^"]*)"', body.group(1)))
    shot = tmp_path / "shot.png"
    subprocess.run([*args, f"--screenshot={shot}", probed.as_uri()], capture_output=True,
                   timeout=180, check=True)  # fmt: skip
    return found, Image.open(shot).convert("RGB")


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_a_run_page_opens_offline_in_a_browser_with_every_plot(trained, tmp_path):
    run, _ = trained
    page = page_of(run, tmp_path / "run.html")
    text = page.read_text()
    ours = re.sub(r"<script>.*?</script>", "", text, count=1, flags=re.S)  # all but plotly.js
    assert not re.search(r"""(src|href)=["']?(https?:)?//|<link|@import""", ours), "links out"
    assert "<script src" not in text
    expected = len(re.findall(r'<div id="plot\d+" class="plot">', text))
    assert expected == 3 * len(read(run).scenes) > 0  # maps, surfaces, profile; no bar chart
    found, shot = _browser(page, tmp_path)
    assert json.loads(found["errors"].replace("&quot;", '"')) == []
    assert json.loads(found["requests"].replace("&quot;", '"')) == []
    assert found["plots"] == found["drawn"] == str(expected)
    pixels = np.asarray(shot)
    assert shot.size == (1400, 1800)
    assert (pixels.std(axis=(0, 1)) > 20).all(), "the screenshot is blank"


def test_a_run_page_shows_each_kept_scene_with_inputs_truth_and_subsets(trained, tmp_path):
    run, metrics = trained
    p = read(run)
    with np.load(run / PREDICTIONS) as z:
        kept = [str(s) for s in z["scene_id"]]
    assert [s.sid for s in p.scenes] == kept[:3]
    scene = p.scenes[0]
    assert scene.views == ["right", "down", "left", "up"] and len(scene.fringes) == 4
    assert scene.subsets.shape == scene.truth_mm.shape and scene.mm_per_px > 0
    lit_by_some = (scene.subsets & 0b1111) > 0
    assert 0.3 < lit_by_some.mean() <= 1.0
    assert dict(p.provenance)["test MAE"].startswith(f"{metrics['test/mae_mm']:.4f}")
    text = page_of(run, tmp_path / "p.html").read_text()
    assert f"scene {scene.sid}" in text and "MAE (mm) in this scene, by height" in text


def test_a_report_page_has_the_tables_bars_with_seeds_and_provenance(tmp_path):
    """The committed mini report (its runs' records and predictions; without the dataset, the
    page says it shows no fringes)."""
    mini = Path(__file__).parents[1] / "experiments" / "results" / "mini"
    p = read(mini)
    assert set(p.tables) == {"views", "table1", "table2"}
    prov = dict(p.provenance)
    assert "synthetic-200x64px" in prov["dataset"] and prov["runs"] == "37"
    assert len(p.scenes) == 3 and len(p.scenes[0].predictions) >= 9
    out = page_of(mini, tmp_path / "mini.html")
    assert out.stat().st_size < 15e6
    for committed in (mini / "page.html", mini.parent / "robustness" / "page.html"):
        assert committed.stat().st_size < 15e6  # the pages beside the committed reports
        assert "Plotly.newPlot" in committed.read_text()
    text = out.read_text()
    assert "Table II: model comparison" in text and "<table>" in text


def test_a_robustness_page_gives_every_series_its_own_colour_and_marker(tmp_path):
    folder = tmp_path / "rob"
    folder.mkdir()
    models = [f"net {k}" for k in range(12)]
    with (folder / "robustness.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["model", "set", "seeds", "mae_mm", "ratio_to_nominal"])
        for k, m in enumerate(models):
            w.writerow([m, "nominal", 2, 0.2, 1.0])
            w.writerow([m, "gamma:2.2", 2, 0.3, 1.5 + k / 10])
            w.writerow([m, "dead_view:right", 2, 0.4, 2.0])
    from odmv.page.plots import robustness_curves

    fig = robustness_curves(read(folder).robustness)
    styles = {(t.line.color, t.marker.symbol) for t in fig.data if t.showlegend}
    assert len(styles) == len(models)
    gamma = next(t for t in fig.data if t.name == "net 3" and t.showlegend)
    assert list(gamma.x) == [1.0, 2.2] and list(gamma.y) == [1.0, pytest.approx(1.8)]
    assert "page.html" in str(page_of(folder))


def test_a_predict_page_compares_with_the_scene_truth(trained, tiny_dataset, tmp_path):
    from helpers import compose_config

    run, metrics = trained
    scene = sorted((tiny_dataset / "scenes").iterdir())[0]
    cfg = compose_config(
        "predict", [f"ckpt_path={run / metrics['best_checkpoint']}", f"input={scene}",
                    f"out={tmp_path / 'pred'}"],
    )  # fmt: skip
    predict(cfg)
    p = read(tmp_path / "pred")
    (s,) = p.scenes
    assert s.truth_mm is not None and len(s.fringes) == 4
    assert "page.html" in page_of(tmp_path / "pred").name


def test_the_view_app_reports_a_bad_folder_in_one_line(tmp_path):
    (tmp_path / "empty").mkdir()
    for args, words in (
        ([str(tmp_path / "empty")], "not a run, report or predict output folder"),
        ([str(tmp_path / "nowhere")], "no such folder"),
        ([str(tmp_path / "empty"), f"out={tmp_path / 'x.png'}"], "a page is an .html file"),
        ([str(tmp_path / "empty"), "size=3"], "unknown"),
    ):
        r = subprocess.run([sys.executable, "-m", "odmv.view", *args], capture_output=True,
                           text=True)  # fmt: skip
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.splitlines()) == 1
    with pytest.raises(PageError):
        read(tmp_path / "empty")


def test_the_error_colour_scale_reads_fine_and_gross_errors_alike():
    e = np.array([-10.0, -0.05, 0.0, 0.05, 10.0], np.float32)
    c = signed_log(e)
    assert c[2] == 0 and c[3] == -c[1] and c[4] == -c[0]
    assert c[3] == pytest.approx(np.log10(2)) and c[4] > 3 * c[3]


def test_markdown_tables_become_html_tables():
    md = "# t\n\n- a `b`\n\n| x | y |\n|---|---:|\n| 1 | **2** |\n\n![fig](f.png)\n"
    out = markdown_html(md)
    assert "<h2>t</h2>" in out and "<li>a <code>b</code></li>" in out
    assert "<table><tr><th>x</th><th>y</th></tr><tr><td>1</td><td><b>2</b></td></tr></table>" in out
    assert "f.png" not in out


def test_the_robustness_png_gives_each_model_its_own_line_style_and_keeps_data_clear(
    tmp_path, monkeypatch
):
    """matplotlib's ten-colour cycle once gave two of eleven series one colour, and the legend
    sat over the first panel's data."""
    import matplotlib.pyplot as plt

    from odmv.study import robustness

    rows = [
        {"model": f"net {k}", "set": s, "ratio_to_nominal": str(r)}
        for k in range(12)
        for s, r in (("nominal", 1.0), ("gamma:2.2", 1.5 + k / 10), ("defocus:1.5", 2.0))
    ]
    drawn = {}
    monkeypatch.setattr(plt, "close", lambda fig: drawn.setdefault("fig", fig))
    robustness.figure(rows, tmp_path / "r.png")
    fig = drawn["fig"]
    lines = [ln for ln in fig.axes[0].get_lines() if ln.get_label().startswith("net")]
    assert len({(str(ln.get_color()), ln.get_marker()) for ln in lines}) == 12
    assert not fig.axes[0].get_legend() and len(fig.legends) == 1  # below the panels
    assert Image.open(tmp_path / "r.png").size[0] > 500
