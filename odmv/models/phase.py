"""The phase head (beyond the paper; ``head=phase``): nets that decode the fringes.

A depth head regresses depth from the fringes and may learn the objects' shapes instead of
reading the phase. The phase head makes every view's fringe the thing the net must read: per
view, it predicts the input image's wrapped phase as (sin, cos) and a confidence. :func:`fuse`
then turns each view's phase into depth through the rig's calibration
(odmv.classical.geometry; the maps
travel with the batch) and blends the views' depths and the net's own regressed depth (the
fallback where no projector lights a pixel) by a softmax of their confidences.

The wrapped phase fixes the depth up to whole fringe periods (about 11 mm of height on the twin
at 64 px); the fringe order comes from a coarse estimate that need only be right to half a
period, as a coarse fringe serves temporal unwrapping: by default the net's own regressed depth
(``orders`` 0), or (``orders`` K > 0) a classification of each view's order over K orders
centred on the reference plane. The regressed depth measured better on the quickstart screen
(docs/findings.md): a classifier is least sure exactly where the truth lies between two orders,
and one wrong order costs a whole period.

Outputs a net adds with the phase head: ``phase`` (B x 2S x H x W, each view's sin and cos in
[-1, 1]), ``confidence`` (B x (S + 1) x H x W logits: the views, then the regressed depth) and
with ``orders`` > 0 ``order`` (B x S x K x H x W logits).
"""

from __future__ import annotations

import torch
import torch.nn as nn

from odmv.classical.geometry import (
    depth_from_offset,
    fraction_from_phase,
    offset_from_depth,
    offset_from_phase,
)
from odmv.models.blocks import inner_softmax

#: every head a net can have (``head=NAME``; null: the paper's depth head) -> whether the net
#: reads the rig's triangulation maps beside its images: the data module then carries them
#: (``data.calibration``) and the forward pass, ONNX graph and predictor take them
HEADS = {"depth": False, "phase": True}


def check_head(head: str | None, orders: int | None = None) -> tuple[str, int]:
    """``head`` and ``orders`` with their defaults (None: the depth head; 0 orders, i.e. the
    regressed depth gives the order), checked."""
    head, orders = head or "depth", orders or 0
    if head not in HEADS:
        raise ValueError(f"head={head}: unknown; choose {' or '.join(HEADS)}")
    if orders < 0:
        raise ValueError(f"phase_orders: {orders} must be 0 (the regressed depth) or more")
    return head, orders


def lowest_order(orders: int) -> int:
    """The classes are the orders lowest_order .. lowest_order + orders - 1, centred on 0
    (the order of a view's offset is its nearest whole number of periods)."""
    return -(orders // 2)


class PhaseHead2d(nn.Module):
    """Views stacked as channels: full-resolution features B x C x H x W -> every view's phase,
    order and confidence, and the regressed depth's confidence."""

    def __init__(self, ch: int, n_views: int, orders: int):
        super().__init__()
        self.n_views, self.orders = n_views, orders
        self.body = nn.Sequential(nn.Conv2d(ch, ch, 3, padding=1), nn.LeakyReLU(0.1, inplace=True))
        self.out = nn.Conv2d(ch, n_views * (3 + orders) + 1, 1)

    def forward(self, f: torch.Tensor) -> dict:
        y = self.out(self.body(f)).float()
        s, k = self.n_views, self.orders
        per_view = y[:, : s * (3 + k)].unflatten(1, (s, 3 + k))  # B x S x (3 + K) x H x W
        return _outputs(per_view, y[:, -1:], k)


def _outputs(per_view: torch.Tensor, regressed_logit: torch.Tensor, orders: int) -> dict:
    """Per-view channels (B x S x (3 + K) x H x W: sin, cos, K order logits, confidence) and
    the regressed depth's confidence logit (B x 1 x H x W) as the head's outputs."""
    out = {
        "phase": torch.tanh(per_view[:, :, :2]).flatten(1, 2),
        "confidence": torch.cat([per_view[:, :, -1], regressed_logit], 1),
    }
    return out | ({"order": per_view[:, :, 2 : 2 + orders]} if orders else {})


class PhaseHead3d(nn.Module):
    """A view axis in the features (B x C x S x H x W, ODMV-Net): one head shared by the views;
    the regressed depth's confidence comes from the fused 2D features (B x C2 x H x W)."""

    def __init__(self, ch: int, fused_ch: int, orders: int):
        super().__init__()
        self.orders = orders
        self.body = nn.Sequential(
            nn.Conv3d(ch, ch, (1, 3, 3), padding=(0, 1, 1)), nn.LeakyReLU(0.1, inplace=True)
        )
        self.out = nn.Conv3d(ch, 3 + orders, 1)
        self.regressed = nn.Conv2d(fused_ch, 1, 1)

    def forward(self, f: torch.Tensor, fused: torch.Tensor, view_logits=None) -> dict:
        """``view_logits`` (B x S x H x W or None): added to the views' confidences (ODMV-Net's
        fusion weights, as logits)."""
        y = self.out(self.body(f)).float().transpose(1, 2)  # B x S x (3 + K) x H x W
        if view_logits is not None:
            y = torch.cat([y[:, :, :-1], (y[:, :, -1] + view_logits.float())[:, :, None]], 2)
        return _outputs(y, self.regressed(fused).float(), self.orders)


def reads_maps(head: str | None) -> bool:
    """Whether a net with ``head`` (its config's; None: the depth head) reads the rig's
    triangulation maps beside its images (:data:`HEADS`)."""
    return HEADS[check_head(head)[0]]


def view_depths(out: dict, maps: torch.Tensor, coarse_mm: torch.Tensor) -> torch.Tensor:
    """Each view's depth (B x S x H x W, mm) from its wrapped phase and its order: from the
    order logits where the net has them, else from the coarse depth ``coarse_mm`` (B x 1 x H x
    W, mm; the regressed depth) seen through each view's triangulation."""
    sin_cos = out["phase"].unflatten(1, (maps.shape[1], 2))
    fraction = fraction_from_phase(sin_cos, maps)
    if "order" in out:
        order = out["order"]
        levels = torch.arange(order.shape[2], device=order.device, dtype=order.dtype)
        levels = levels + lowest_order(order.shape[2])  # each class's centre, in periods
        coarse = (inner_softmax(order, 2) * levels[:, None, None]).sum(2)
    else:
        coarse = offset_from_depth(coarse_mm, maps) / maps[:, :, 1]
    return depth_from_offset(offset_from_phase(fraction, coarse, maps), maps)


def candidates_kept(available: torch.Tensor) -> torch.Tensor:
    """Which of the blend's candidates exist (B x (S + 1) x 1 x 1 bool) for ``available`` (B x
    S bool): the views present, and the regressed depth always."""
    keep = torch.cat([available, available.new_ones(available.shape[0], 1)], 1)
    return keep[..., None, None]


def fuse(out: dict, maps: torch.Tensor, norm, available=None) -> dict:
    """The net's outputs with ``depth`` the confidence-weighted blend of the views' depths and
    the regressed one (kept as ``regressed``, and in mm as ``regressed_mm``), ``view_depth_mm``
    (B x S x H x W) and the
    blend's ``weights`` (B x (S + 1) x H x W). ``norm``: the net's depth units (``depth``: mm ->
    units, ``depth_mm``: back); ``available`` (B x S bool or None): a missing view gets no
    weight. Runs in float32."""
    with torch.autocast(maps.device.type, enabled=False):
        out = {k: v.float() if torch.is_tensor(v) else v for k, v in out.items()}
        regressed_mm = norm.depth_mm(out["depth"])
        depth_mm = view_depths(out, maps.float(), regressed_mm)
        candidates = torch.cat([norm.depth(depth_mm), out["depth"]], 1)
        logits = out["confidence"]
        if available is not None:
            logits = logits.masked_fill(~candidates_kept(available), float("-inf"))
        weights = inner_softmax(logits, 1)
        # a view's depth can be far off where it is unlit; its weight is then ~0, never NaN
        fused = (weights * torch.nan_to_num(candidates)).sum(1, keepdim=True)
    return out | {
        "depth": fused,
        "regressed": out["depth"],
        "regressed_mm": regressed_mm,
        "view_depth_mm": depth_mm,
        "weights": weights,
    }
