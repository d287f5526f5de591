"""OmegaConf resolvers the configs use; imported by every Hydra entry point."""

from __future__ import annotations

from omegaconf import ListConfig, OmegaConf

from odmv.rig import VIEW_SETS, check_views


def view_list(views) -> list[str]:
    """``views`` as a count (the paper's S=1..4 subsets) or a list of names -> names in order."""
    if isinstance(views, (list, tuple, ListConfig)):
        return list(check_views([str(v) for v in views]))
    try:
        return list(VIEW_SETS[int(views)])
    except (KeyError, ValueError):
        raise ValueError(
            f"views={views!r}: use 1, 2, 3 or 4 (the paper's subsets) or a list of names"
        ) from None


if not OmegaConf.has_resolver("odmv.views"):
    OmegaConf.register_new_resolver("odmv.views", view_list)
