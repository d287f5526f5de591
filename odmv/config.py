"""Where the configs live, the net registry, the OmegaConf resolvers the configs use, and
:func:`app`, the Hydra entry point every app is (its composition errors in one line)."""

from __future__ import annotations

import functools
import hashlib
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from omegaconf import DictConfig, ListConfig, OmegaConf

from odmv.cli import WRAPPERS, hydra_line, note_existing_outputs, traceback_wanted
from odmv.data.reference import view_channels as reference_channels
from odmv.models.odmvnet import TABLE_I
from odmv.models.phase import reads_maps
from odmv.rig import VIEW_SETS, check_views
from odmv.sim.shifts import KINDS

#: the Hydra config tree every app composes from: conf/ of the checkout this module is in (as
#: odmv/conf links to it), or the copy an installed wheel carries there. A path of this very
#: tree rather than pkg://odmv.conf, which an editable install would resolve to its own
#: checkout even for a worktree run by PYTHONPATH.
CONF_DIR = str(Path(__file__).resolve().parent / "conf")
T = TypeVar("T")


def compose_app(name: str, overrides: list[str], hydra_cfg: bool = False) -> DictConfig:
    """App ``name``'s config for ``overrides``, inside a running Hydra app or in a fresh one."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return compose(name, overrides=overrides, return_hydra_config=hydra_cfg)
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(name, overrides=overrides, return_hydra_config=hydra_cfg)


def compose_train(overrides: list[str], hydra_cfg: bool = False) -> DictConfig:
    """The train config for ``overrides`` (:func:`compose_app`)."""
    return compose_app("train", overrides, hydra_cfg)


def model_configs() -> dict[str, DictConfig]:
    """The net registry: every model config (conf/model/NAME.yaml) by NAME, as written. A net is
    its class plus its config; a config whose defaults list builds on another (unet_s4) is a
    variant of that net. ``model.table2`` makes it a row of Table II."""
    return {p.stem: OmegaConf.load(p) for p in sorted(Path(CONF_DIR, "model").glob("*.yaml"))}


def display_name(model: str) -> str:
    """How reports and pages name the net whose ``model.name`` is ``model`` (its config's
    ``model.display``; the name itself where none says)."""
    for c in model_configs().values():
        if c.model.get("name") == model and c.model.get("display"):
            return str(c.model.display)
    return model


def nets() -> list[str]:
    """The nets: model configs that are not variants of another."""
    return [name for name, c in model_configs().items() if "defaults" not in c]


def baselines() -> list[str]:
    """The nets ODMV-Net is compared against."""
    return [name for name in nets() if name != "odmvnet"]


def contenders(extra=None) -> ListConfig:
    """Table II's rows in their order: every model config with a ``table2`` entry, without the
    ones marked ``extra`` (rows beyond the paper) unless ``extra`` is given."""
    rows = {
        name: c.model.table2
        for name, c in model_configs().items()
        if c.get("model", {}).get("table2") is not None
    }
    keep = [n for n, r in rows.items() if extra is not None or not r.get("extra", False)]
    return ListConfig(sorted(keep, key=lambda n: rows[n].order))


def view_list(views) -> ListConfig:
    """``views`` as a count (the paper's S=1..4 subsets) or a list of names -> names in order.

    Returned as a ListConfig so that ``OmegaConf.resolve`` can store it in place."""
    if isinstance(views, (list, tuple, ListConfig)):
        return ListConfig(list(check_views([str(v) for v in views])))
    try:
        return ListConfig(list(VIEW_SETS[int(views)]))
    except (KeyError, ValueError):
        raise ValueError(
            f"views={views!r}: use 1, 2, 3 or 4 (the paper's subsets) or a list of names"
        ) from None


#: settings whose null (off) state leaves a node's hash as it was before they existed
NULL_OFF = ("randomize",)


def settings_hash(node) -> str:
    """Short stable hash of a config node (ignoring ``workers``, and the settings of NULL_OFF
    when null), to name derived folders."""
    d = OmegaConf.to_container(node, resolve=True) if not isinstance(node, dict) else node
    d = {k: v for k, v in d.items() if k != "workers" and not (k in NULL_OFF and v is None)}
    return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:8]


def n_views(views) -> int:
    return len(view_list(views))


def view_channels(reference) -> int:
    """Network input channels per view (odmv.data.reference)."""
    return reference_channels(reference)


def in_channels(views, reference, view_dropout=None) -> int:
    """Input channels of a 2D net that stacks every view's channels (and, trained with
    ``view_dropout``, each view's availability: odmv.data.views)."""
    return n_views(views) * (view_channels(reference) + (view_dropout is not None))


def availability(view_dropout):
    """ODMV-Net's ``availability`` switch: True with ``view_dropout``, else None (off)."""
    return True if view_dropout is not None else None


def phase_head(head):
    """The data module's ``calibration`` switch: True where the head reads the rig's maps
    (odmv.models.phase.HEADS), else None (off)."""
    return True if reads_maps(head) else None


def phase_views(head, views):
    """A baseline's ``n_views``: the view count with ``head=phase`` (its phase head's outputs),
    else None."""
    return n_views(views) if phase_head(head) else None


def first_set(*values):
    """The first value that is not null: ``${odmv.first:${out},DEFAULT}``."""
    return next((v for v in values if v is not None), None)


def on_gpu(accelerator) -> bool:
    """Whether a trainer with this accelerator runs on GPUs (SyncBatchNorm needs them)."""
    if str(accelerator) in ("gpu", "cuda"):
        return True
    if str(accelerator) == "auto":
        import torch

        return torch.cuda.is_available()
    return False


def cpu_precision() -> str:
    """``bf16-mixed`` on a CPU with bfloat16 instructions (AVX512-BF16 or AMX), where it trains
    the quickstart net faster at the same accuracy (docs/performance.md); ``32`` elsewhere, where
    bfloat16 arithmetic is emulated and nothing here shows that it pays."""
    import torch

    native = (
        getattr(torch.cpu, "_is_avx512_bf16_supported", lambda: False)()
        or getattr(torch.cpu, "_is_amx_tile_supported", lambda: False)()
    )
    return "bf16-mixed" if native else "32"


def randomize_profile(name):
    """A domain-randomization profile (conf/randomize/NAME.yaml) as {shift: [low, high]};
    None for null."""
    if name is None:
        return None
    path = Path(CONF_DIR, "randomize", f"{name}.yaml")
    if not path.is_file():
        known = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ValueError(f"data.randomize={name}: no such profile; choose from {', '.join(known)}")
    return OmegaConf.load(path)


def csv_list(values) -> str:
    """[0, 1] -> "0,1": a list as a Hydra sweep value (sweep configs' seeds)."""
    return ",".join(str(v) for v in values)


def table_i_rows() -> str:
    """Table I's row keys as a Hydra sweep value (conf/sweep/ablation.yaml)."""
    return ",".join(row.key for row in TABLE_I)


def _register_options() -> None:
    """``ablation=KEY`` for each Table I row and ``shift=NAME`` for each shift: config groups
    built from their one table each (odmv.models.odmvnet.TABLE_I, odmv.sim.shifts.KINDS; no
    file per option), so a wrong name gets Hydra's list of the options."""
    from hydra.core.config_store import ConfigStore

    store = ConfigStore.instance()
    for row in TABLE_I:
        store.store(group="ablation", name=row.key, node={"ablation": row.key}, package="_global_")
    for name, kind in KINDS.items():
        store.store(
            group="shift", name=name, node={"name": name, "strength": kind.example, "seed": 0}
        )


for _name, _fn in (
    ("odmv.csv", csv_list),
    ("odmv.table_i", table_i_rows),
    ("odmv.first", first_set),
    ("odmv.on_gpu", on_gpu),
    ("odmv.cpu_precision", cpu_precision),
    ("odmv.view_channels", view_channels),
    ("odmv.in_channels", in_channels),
    ("odmv.views", view_list),
    ("odmv.n_views", n_views),
    ("odmv.hash", settings_hash),
    ("odmv.contenders", contenders),
    ("odmv.randomize", randomize_profile),
    ("odmv.availability", availability),
    ("odmv.phase_head", phase_head),
    ("odmv.phase_views", phase_views),
):
    if not OmegaConf.has_resolver(_name):
        OmegaConf.register_new_resolver(_name, _fn)
_register_options()


# ------------------------------------------------------------------ the apps' entry point
def app(config_name: str) -> Callable:
    """``hydra.main`` of an entry point (config ``odmv/conf/<config_name>.yaml``), with Hydra's
    own errors in one line and top-level keys added with ``+`` that the app does not have
    refused (Hydra would add them, and the app would ignore them)."""
    import hydra

    def decorate(fn: Callable) -> Callable:
        @functools.wraps(fn)
        def checked(cfg):
            added = unknown_added_keys()
            if added:
                if traceback_wanted():
                    raise ValueError(added)
                print(f"error: {added}", file=sys.stderr)
                sys.exit(2)
            return fn(cfg)

        entry = hydra.main(version_base="1.3", config_path=CONF_DIR, config_name=config_name)
        wrapped = entry(checked)

        @functools.wraps(fn)
        def main(*args, **kwargs):
            from hydra._internal import utils

            note_existing_outputs(sys.argv[1:])
            original = utils.run_and_report
            utils.run_and_report = _report_in_one_line
            try:
                return wrapped(*args, **kwargs)
            finally:
                utils.run_and_report = original

        return main

    return decorate


def _report_in_one_line(func: Callable[[], T]) -> T:
    """Hydra's ``run_and_report`` (it runs composition and the app), one line instead of its
    option lists and tracebacks."""
    try:
        return func()
    except Exception as exc:
        if traceback_wanted():
            raise
        from hydra.errors import HydraException

        line = hydra_line(exc)
        if not isinstance(exc, (ValueError, OSError, HydraException, *WRAPPERS)):
            line += f" ({type(exc).__name__}; HYDRA_FULL_ERROR=1 shows where)"
        print(f"error: {line}", file=sys.stderr)
        sys.exit(2)


def unknown_added_keys() -> str | None:
    """The line refusing top-level keys that the command line added with ``+`` (``+out=DIR``
    where the app has no ``out``), or None; config groups (``+experiment=...``) and keys inside
    existing settings (``+trainer.max_steps=...``, ``+rows.NAME=...``) are the app's own."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if not HydraConfig.initialized():
        return None
    groups = set(HydraConfig.get().runtime.choices)
    parsed = OverridesParser.create().parse_overrides(list(HydraConfig.get().overrides.task))
    added = [
        o.key_or_group
        for o in parsed
        if o.is_add() and "." not in o.key_or_group and o.key_or_group not in groups
    ]
    if not added:
        return None
    return f"{added[0]}: not a setting of this app (added with +{added[0]}=, it would be ignored)"
