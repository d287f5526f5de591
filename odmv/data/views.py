"""Missing views (beyond the paper): one model for any set of working projectors.

A net trained with ``view_dropout`` takes, after each view's channels, one more channel: the
view's availability, 1 where its projector worked and 0 where it is missing. A missing view's
channels are all zero, its availability too, so the net knows it is missing rather than dark;
ODMV-Net then gives it no weight in its fusion (odmv.models.blocks.OcclusionAwareFusion), and
nets that take views as channels read the zeros and the flag. ``ViewDropout`` drops views of
training samples at random; evaluation and prediction mark the views a capture lacks.
"""

from __future__ import annotations

import torch


def with_availability(inputs: torch.Tensor, available: torch.Tensor) -> torch.Tensor:
    """``inputs`` (..., S * C, H, W, each view's channels together) and ``available`` (..., S,
    0/1) -> (..., S * (C + 1), H, W): each view's channels times its availability, then the
    availability as a channel of its own."""
    s = available.shape[-1]
    x = inputs.unflatten(-3, (s, inputs.shape[-3] // s))  # ..., S, C, H, W
    flag = available.to(x)[..., None, None, None].expand(*x.shape[:-3], 1, *x.shape[-2:])
    return torch.cat([x * flag, flag], -3).flatten(-4, -3)


def drop(sample: dict, keep: torch.Tensor) -> dict:
    """``sample`` (whose ``inputs`` carry availability) with the views where ``keep`` is False
    made missing: their channels and flag zero, their ``available`` 0."""
    out = dict(sample)
    s = keep.shape[0]
    x = sample["inputs"].unflatten(0, (s, sample["inputs"].shape[0] // s))
    out["inputs"] = (x * keep[:, None, None, None].to(x)).flatten(0, 1)
    out["available"] = sample["available"] * keep.to(sample["available"])
    return out


class MissingViews(torch.utils.data.Dataset):
    """Each item of ``base`` with the views where ``keep`` is False missing (a capture that
    lacks them, for a net trained with view dropout)."""

    def __init__(self, base, keep: torch.Tensor):
        self.base, self.keep = base, keep

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> dict:
        return drop(self.base[i], self.keep)


class ViewDropout(torch.utils.data.Dataset):
    """Each item of ``base`` with each view dropped with probability ``p``, at least one kept
    (torch's generator: a seeded run drops the same views)."""

    def __init__(self, base, p: float):
        if not 0 <= p < 1:
            raise ValueError(f"data.view_dropout: {p} is not a probability below 1")
        self.base, self.p = base, p

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> dict:
        sample = self.base[i]
        s = sample["available"].shape[0]
        keep = torch.rand(s) >= self.p
        if not keep.any():
            keep[torch.randint(s, ())] = True
        return drop(sample, keep)
