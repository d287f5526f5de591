"""odmv as an installed library: a wheel built from the checkout, installed into a fresh venv,
runs its apps from an empty folder with the configs it carries, writing only there."""

import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def run(cmd, cwd, timeout=600):
    done = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, f"{cmd}: {done.stdout[-2000:]}{done.stderr[-2000:]}"
    return done.stdout


@pytest.mark.slow
def test_the_wheel_runs_the_apps_from_any_folder(tmp_path):
    source = tmp_path / "source"  # a copy: building writes build/ beside the sources
    shutil.copytree(ROOT / "odmv", source / "odmv", symlinks=True)
    shutil.copytree(ROOT / "conf", source / "conf")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
         str(source), "-w", str(tmp_path / "dist")], tmp_path)  # fmt: skip
    (wheel,) = (tmp_path / "dist").glob("odmv-*.whl")
    venv = tmp_path / "venv"
    run([sys.executable, "-m", "venv", "--without-pip", str(venv)], tmp_path)
    python = venv / "bin" / "python"
    purelib = "import sysconfig; print(sysconfig.get_paths()['purelib'])"
    site = Path(run([str(python), "-c", purelib], tmp_path).strip())
    # the dependencies (torch and the rest) come from this venv; odmv only from the wheel
    (site / "_dependencies.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps", "-q",
         str(wheel)], tmp_path)  # fmt: skip
    installed = files_of(site)
    assert (
        Path("odmv/conf/train.yaml") in installed
        and Path("odmv/conf/model/uhrnet.yaml") in installed
    )

    work = tmp_path / "work"
    work.mkdir()
    where = run([str(python), "-c", "import odmv; print(odmv.__file__)"], work)
    assert where.startswith(str(site))
    job = run([str(python), "-m", "odmv.train", "model=uhrnet", "--cfg", "job"], work)
    assert "_target_: odmv.models.UHRNet" in job
    # a user's own presets beside the ones the package carries
    (work / "mine" / "experiment").mkdir(parents=True)
    (work / "mine" / "experiment" / "bench.yaml").write_text("# @package _global_\nseed: 1234\n")
    job = run([str(python), "-m", "odmv.train", "experiment=bench",
               f"hydra.searchpath=[file://{work / 'mine'}]", "--cfg", "job"], work)  # fmt: skip
    assert "seed: 1234" in job
    run([str(python), "-m", "odmv.simulate", "out=ds", "scenes=2", "resolution=32", "workers=1",
         "progress=false", "splits=null"], work)  # fmt: skip
    assert "ok, 2 scenes" in run([str(python), "-m", "odmv.validate", "ds"], work)
    assert files_of(site) == installed  # nothing written into the package


def files_of(site: Path) -> list[Path]:
    """The installed package's files (Python's own byte-code caches aside)."""
    return sorted(
        p.relative_to(site) for p in (site / "odmv").rglob("*") if "__pycache__" not in p.parts
    )
