"""The package's shape (docs/layout.md): apps at the top of odmv/, library code in subpackages
below them, and every import runs downward."""

import ast
from pathlib import Path

import odmv

PACKAGE = Path(odmv.__file__).parent
#: what ``python -m odmv.X`` runs
APPS = {
    "calibration", "convert", "demo", "evaluate", "export", "predict", "report", "reproduce",
    "simulate", "train", "validate", "view",
}  # fmt: skip
#: the leaves every layer imports
LEAVES = {"__init__", "cli", "config", "rig"}


def _imported(path: Path) -> set[str]:
    """Every odmv module ``path`` imports (at its top or inside a function)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names |= {f"{node.module}.{a.name}" for a in node.names}
    return {n for n in names if n.split(".")[0] == "odmv"}


def test_the_top_level_holds_the_apps_and_the_named_leaves_only():
    top = {p.stem for p in PACKAGE.glob("*.py")}
    assert top == APPS | LEAVES, f"move {sorted(top - APPS - LEAVES)} into a subpackage"
    for app in APPS:
        assert "def main(" in (PACKAGE / f"{app}.py").read_text(), f"odmv.{app} has no main"


def test_no_library_module_imports_an_app():
    upward = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.parent == PACKAGE and path.stem in APPS:
            continue
        for name in _imported(path):
            parts = name.split(".")
            if len(parts) > 1 and parts[1] in APPS:
                upward.append(f"{path.relative_to(PACKAGE.parent)} imports {name}")
    assert not upward, "\n".join(upward)


def test_no_library_module_runs_an_app_as_a_subprocess():
    """``[sys.executable, "-m", "odmv.evaluate", ...]`` in the library: the library calls the
    function the app calls instead."""
    runs = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.parent == PACKAGE and path.stem in APPS:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Constant) and node.value in {f"odmv.{a}" for a in APPS}:
                runs.append(f"{path.relative_to(PACKAGE.parent)} runs {node.value}")
    assert not runs, "\n".join(runs)


def test_an_app_imports_no_other_app_but_the_demo_its_steps():
    """What two apps share lives in the library; the demo alone runs train and evaluate."""
    across = []
    for app in sorted(APPS - {"demo"}):
        for name in _imported(PACKAGE / f"{app}.py"):
            parts = name.split(".")
            if len(parts) > 1 and parts[1] in APPS - {app}:
                across.append(f"odmv/{app}.py imports {name}")
    assert not across, "\n".join(across)


def test_the_import_check_sees_an_upward_import(tmp_path):
    """The check above finds imports inside functions and `from odmv import app` alike."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from odmv import train\n    import odmv.export as e\n")
    assert {"odmv.train", "odmv.export"} <= _imported(probe)
