"""Training objective of the paper, eqs. (1)-(5), for any net's output dict.

L = L_main + sum_k lambda_aux[k] L_aux_k + lambda_view L_view (+ lambda_occ L_occ, beyond the
paper: BCE between the OCD masks and the simulator's lit masks, 0 by default), with
L_depth = alpha (1 - SSIM) + (1 - alpha) L1 (eqs. 2-4, kornia's SSIM, 11 px Gaussian window)
and L_view = MSE against the normalized input fringes (eq. 5). Terms whose outputs a net does
not produce are skipped. Auxiliary targets are the depth taken at each scale's pixel centres
(the same rule the data module resizes with), so no target depth is invented at an edge.
Pixels without ground truth (NaN depth, e.g. an imported dataset's background) add no error:
the L1 term averages over valid pixels, and SSIM sees the prediction there.

With the phase head (``head=phase``, odmv.models.phase; beyond the paper) the main depth is the
fused one, and each view is supervised on its lit pixels: its phase (the ``phase`` term), its
fringe order where the net classifies it (``order``, cross-entropy against the nearest whole
number of periods between the true projector coordinate and the reference plane's) and
its confidence (``confidence``, BCE against the lit mask, or against the view's depth lying
within ``confidence_tol_mm`` of the truth); the net's own regressed depth, the fallback of the
fusion, keeps a depth loss of its own (``regressed``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from kornia.metrics import ssim

from odmv.classical.geometry import offset_from_coord
from odmv.models.phase import candidates_kept, lowest_order

# the weights of the terms beyond the main depth loss, and the net output each term needs: a
# weight is read only for a net with that output (each net lists its terms in LOSS_TERMS)
OPTIONAL_TERMS = {"aux": "aux", "view": "views", "occlusion": "occlusion", "phase": "phase"}
# the loss settings that only the phase head reads (besides its ``phase`` term)
PHASE_TERMS = (
    "phase",
    "order",
    "confidence",
    "confidence_target",
    "confidence_tol_mm",
    "regressed",
)
CONFIDENCE_TARGETS = ("lit", "error", "nearest")


@dataclass
class LossWeights:
    alpha: float = 0.8  # SSIM share of the depth loss (eq. 2)
    aux: list[float] = field(default_factory=lambda: [0.5, 0.3])  # lambda_1, lambda_2 (eq. 1)
    view: float = 0.2  # lambda_3
    occlusion: float = 0.0  # OCD supervision with lit masks (not in the paper)
    phase: float = 1.0  # wrapped-phase head of multi-task baselines (MTLNet) and head=phase
    order: float = 1.0  # head=phase: fringe-order cross-entropy
    confidence: float = 1.0  # head=phase: confidence BCE
    confidence_target: str = "lit"  # lit | error | nearest
    confidence_tol_mm: float = 0.2  # the error target's tolerance
    regressed: float = 1.0  # head=phase: depth loss of the regressed fallback
    ssim_window: int = 11
    depth_range: float = 2.0  # dynamic range of normalized depth, SSIM's L

    def __post_init__(self):
        if self.confidence_target not in CONFIDENCE_TARGETS:
            raise ValueError(
                f"loss.confidence_target: {self.confidence_target!r} unknown; choose from "
                f"{', '.join(CONFIDENCE_TARGETS)}"
            )


def resize_target(t: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Depth or mask at a coarser scale: the sample nearest each output pixel centre."""
    if t.shape[-2:] == size:
        return t
    return F.interpolate(t, size=size, mode="nearest-exact")


def depth_loss(pred: torch.Tensor, target: torch.Tensor, w: LossWeights) -> dict[str, torch.Tensor]:
    target = resize_target(target, pred.shape[-2:])
    valid = torch.isfinite(target)
    if not valid.all():  # pixels without ground truth (NaN) take the prediction: no error
        target = torch.where(valid, target, pred.detach())
    side = min(pred.shape[-2:])
    window = min(w.ssim_window, side if side % 2 else side - 1)  # odd, no larger than the map
    l1 = (pred - target).abs().sum() / valid.sum().clamp_min(1)
    # at alpha 0 (pure L1) SSIM is only reported: no graph, no backward through its filters
    with torch.set_grad_enabled(torch.is_grad_enabled() and w.alpha > 0):
        l_ssim = 1 - ssim(pred, target, window, max_val=w.depth_range).mean()
    loss = w.alpha * l_ssim + (1 - w.alpha) * l1 if w.alpha else l1
    return {"loss": loss, "ssim": l_ssim, "l1": l1}


def composite_loss(out: dict, batch: dict, w: LossWeights) -> dict[str, torch.Tensor]:
    """All loss terms (keys ``main``, ``aux1``, ..., ``view``, ``occlusion``, ``phase``) and
    their weighted sum under ``loss``."""
    terms = {}
    main = depth_loss(out["depth"], batch["depth"], w)
    terms.update(main=main["loss"], main_ssim=main["ssim"], main_l1=main["l1"])
    total = main["loss"]
    for k, (aux, lam) in enumerate(zip(out.get("aux", []), w.aux, strict=False), start=1):
        terms[f"aux{k}"] = depth_loss(aux, batch["depth"], w)["loss"]
        total = total + lam * terms[f"aux{k}"]
    # a missing view (odmv.data.views) is neither reconstructed nor phase-supervised
    available = batch.get("available")
    if "views" in out and w.view:
        if available is None:
            terms["view"] = F.mse_loss(out["views"], batch["fringes"])
        else:
            keep = available[..., None, None].expand_as(batch["fringes"])
            err = (out["views"] - batch["fringes"]) ** 2 * keep
            terms["view"] = err.sum() / keep.sum().clamp_min(1)
        total = total + w.view * terms["view"]
    if "occlusion" in out and w.occlusion:
        occ = []
        for m in out["occlusion"]:  # B x 1 x S x h x w vs lit B x S x H x W
            lit = resize_target(batch["lit"], m.shape[-2:])[:, None]
            occ.append(F.binary_cross_entropy(m.clamp(1e-6, 1 - 1e-6), lit))
        terms["occlusion"] = torch.stack(occ).mean()
        total = total + w.occlusion * terms["occlusion"]
    if "phase" in out and w.phase:
        target, lit = (
            batch["phase_target"],
            batch["lit"],
        )  # B x 2S x H x W (sin, cos), B x S x H x W
        mask = lit if available is None else lit * available[..., None, None]
        mask = mask.repeat_interleave(2, dim=1)
        err = (out["phase"] - target) ** 2 * mask
        terms["phase"] = err.sum() / mask.sum().clamp_min(1)
        total = total + w.phase * terms["phase"]
    if "confidence" in out:
        total = total + _phase_head_terms(out, batch, w, available, terms)
    terms["loss"] = total
    return terms


def _phase_head_terms(out, batch, w: LossWeights, available, terms: dict) -> torch.Tensor:
    """The phase head's order, confidence and regressed-depth terms (added to ``terms``);
    returns their weighted sum."""
    lit = batch["lit"] if available is None else batch["lit"] * available[..., None, None]
    lit = lit.bool()
    total = 0.0
    if "order" in out:
        maps, logits = batch["calibration"], out["order"].float()  # B x S x K x H x W
        k = logits.shape[2]
        with torch.no_grad():
            coord = torch.nan_to_num(batch["projector_coord"], nan=0.0)
            order = torch.round(offset_from_coord(coord, maps) / maps[:, :, 1]) - lowest_order(k)
            order = order.clamp(0, k - 1).long()
        ce = F.cross_entropy(logits.transpose(1, 2), order, reduction="none")  # B x S x H x W
        terms["order"] = (ce * lit).sum() / lit.sum().clamp_min(1)
        total = w.order * terms["order"]
    if w.confidence_target == "nearest":
        terms["confidence"] = _nearest_candidate_loss(out, batch, available)
    else:
        conf = out["confidence"][:, : lit.shape[1]].float()
        if w.confidence_target == "lit":
            target = lit.float()
        else:  # the view's own depth within the tolerance of the truth
            err = (out["view_depth_mm"].detach() - batch["depth_mm"]).abs()
            target = (err <= w.confidence_tol_mm).float()
        seen = lit.new_ones(lit.shape)
        if available is not None:
            seen = available[..., None, None].expand_as(lit)
        bce = F.binary_cross_entropy_with_logits(conf, target, reduction="none")
        terms["confidence"] = (bce * seen).sum() / seen.sum().clamp_min(1)
    terms["regressed"] = depth_loss(out["regressed"], batch["depth"], w)["loss"]
    return total + w.confidence * terms["confidence"] + w.regressed * terms["regressed"]


def _nearest_candidate_loss(out: dict, batch: dict, available) -> torch.Tensor:
    """``confidence_target=nearest``: the cross-entropy of the blend's softmax over the views
    and the regressed depth against the candidate nearest the truth at each pixel with one.
    Unlike the per-view targets it trains the regressed depth's confidence too, and ranks the
    candidates against each other rather than each against a fixed tolerance."""
    logits = out["confidence"].float()  # B x (S + 1) x H x W
    with torch.no_grad():
        candidates = torch.cat([out["view_depth_mm"], out["regressed_mm"]], 1).float()
        err = (candidates - batch["depth_mm"]).abs().nan_to_num(float("inf"))
        if available is not None:  # a missing view is no candidate
            missing = ~candidates_kept(available)
            err = err.masked_fill(missing, float("inf"))
        known = torch.isfinite(batch["depth_mm"][:, 0])
        # where there is no truth, the regressed depth (always a candidate) stands in unused
        nearest = torch.where(known, err.argmin(1), err.shape[1] - 1)
    if available is not None:
        logits = logits.masked_fill(missing, float("-inf"))
    ce = F.cross_entropy(logits, nearest, reduction="none")  # B x H x W
    return (ce * known).sum() / known.sum().clamp_min(1)
