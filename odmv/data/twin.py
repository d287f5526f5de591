"""A dataset of the digital twin, as ``python -m odmv.simulate`` makes it: rendered (or its
shards joined), validated, and what a net could recall instead of measure summarized
(odmv.data.prior)."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf

from odmv.data.prior import prior_summary, summary_lines
from odmv.io.manifest import load_manifest
from odmv.io.validation import validate
from odmv.sim.shards import merge, parse_shard, shard_ids
from odmv.sim.writer import SimSettings, simulate


def settings_from_config(cfg: DictConfig) -> SimSettings:
    """Turn the ``simulate`` config into :class:`SimSettings`."""
    return SimSettings.from_dict(OmegaConf.to_container(cfg, resolve=True))


def render_dataset(cfg: DictConfig) -> int:
    """Render (or merge shards), then validate; returns a process exit code."""
    if cfg.get("merge"):
        m = merge(list(cfg.merge), cfg.out)
        print(f"{m.root}: {len(m.scenes)} scenes joined from {len(cfg.merge)} shard folders")
        return check(m.root, cfg.validate)
    s = settings_from_config(cfg)
    shard = parse_shard(cfg.get("shard"))
    rep = simulate(s, workers=cfg.workers, progress=cfg.progress, shard=shard)
    rate = rep.rendered / rep.seconds if rep.seconds > 0 else float("nan")
    part = "" if shard is None else f"shard {shard[0]}/{shard[1]}: "
    print(
        f"{s.out}: {part}rendered {rep.rendered} scenes ({rep.images} fringe images) in "
        f"{rep.seconds:.1f} s ({rate:.2f} scenes/s), {rep.skipped} already complete"
    )
    ids = None if shard is None else shard_ids(load_manifest(s.out), shard)
    code = check(s.out, cfg.validate, ids)
    if not code and shard is None:  # what a net could recall instead of measure
        print("\n".join(summary_lines(prior_summary(load_manifest(s.out)))))
    return code


def check(root, how: str, ids: list[str] | None = None) -> int:
    """Validate (quick: headers; full: every pixel; off) the dataset or the scenes ``ids``."""
    if how == "off":
        return 0
    report = validate(root, deep=how == "full", scene_ids=ids)
    if not report.ok:
        print("\n".join(report.problems))
        return 1
    print(report.summary(root))
    return 0
