"""The package's shape (docs/layout.md): apps at the top of odmv/, library code in subpackages
below them in layers, and every import runs downward: to a lower layer or within its room,
with no circle of modules."""

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
#: the rooms from the bottom up: a module imports its own room and the layers below it only
#: (rooms of one layer not each other); the apps stand above them all
LAYERS = [
    {"odmv", "rig"},
    {"io"},
    {"cli"},
    {"classical", "sim"},
    {"data"},
    {"models"},
    {"importers"},
    {"config"},
    {"training"},
    {"deploy"},
    {"study"},
    {"page"},
]
#: an app is main() and what it prints; its workflow lives in the library
APP_LINES = 80


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


def _modules() -> dict[str, Path]:
    """Every module of the package by dotted name (a package by its own name)."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def _room(module: str) -> str:
    """``odmv.training.run`` -> training; a top-level leaf is its own room; odmv itself odmv."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "odmv"


def _layer(room: str) -> int:
    if room in APPS:
        return len(LAYERS)
    return next(k for k, rooms in enumerate(LAYERS) if room in rooms)


def _module_imports() -> dict[str, set[str]]:
    """Each module -> the package's modules it imports (a name imported from a package that
    is a module of it counts as that module)."""
    modules = _modules()
    out = {}
    for name, path in modules.items():
        found = set()
        for n in _imported(path):
            found.add(
                n
                if n in modules
                else n.rpartition(".")[0]
                if n.rpartition(".")[0] in modules
                else n
            )
        out[name] = {n for n in found if n in modules and n != name}
    return out


def test_every_room_has_a_layer():
    rooms = {_room(m) for m in _modules()} - APPS
    assert rooms == set().union(*LAYERS), "name each room's layer in LAYERS (docs/layout.md)"


def test_every_import_runs_down_the_layers():
    upward = []
    for name, targets in sorted(_module_imports().items()):
        room = _room(name)
        for t in sorted(targets):
            other = _room(t)
            if other != room and _layer(other) >= _layer(room) and room not in APPS:
                upward.append(f"{name} ({room}) imports {t} ({other})")
    assert not upward, "\n".join(upward)


def test_no_circle_of_modules():
    graph = _module_imports()
    done, circles = set(), []

    def visit(name, path):
        if name in path:
            circles.append(" -> ".join([*path[path.index(name) :], name]))
            return
        if name in done:
            return
        for t in sorted(graph[name]):
            visit(t, [*path, name])
        done.add(name)

    for name in sorted(graph):
        visit(name, [])
    assert not circles, "\n".join(circles)


def test_an_app_is_main_and_what_it_prints():
    long = {
        a: n for a in APPS if (n := len((PACKAGE / f"{a}.py").read_text().splitlines())) > APP_LINES
    }
    assert not long, f"move the workflow of {long} into the library"


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


def test_an_app_imports_no_other_app():
    """What two apps share lives in the library (the demo runs training and evaluation)."""
    across = []
    for app in sorted(APPS):
        for name in _imported(PACKAGE / f"{app}.py"):
            parts = name.split(".")
            if len(parts) > 1 and parts[1] in APPS - {app}:
                across.append(f"odmv/{app}.py imports {name}")
    assert not across, "\n".join(across)


def test_tests_reach_the_library_and_run_the_apps():
    """A test imports the library; an app it runs as a user does (its main, or a process)."""
    reached = []
    for path in sorted((PACKAGE.parent / "tests").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                parts = node.module.split(".")
                if parts[0] == "odmv" and len(parts) == 2 and parts[1] in APPS:
                    reached += [
                        f"{path.name}: {node.module}.{a.name}"
                        for a in node.names
                        if a.name != "main"
                    ]
                elif node.module == "odmv":
                    reached += [f"{path.name}: odmv.{a.name}" for a in node.names if a.name in APPS]
    assert not reached, "\n".join(reached)


def test_the_import_check_sees_an_upward_import(tmp_path):
    """The check above finds imports inside functions and `from odmv import app` alike."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from odmv import train\n    import odmv.export as e\n")
    assert {"odmv.train", "odmv.export"} <= _imported(probe)
