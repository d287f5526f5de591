"""Depth errors in mm (torchmetrics), as the paper reports them.

MAE and MSE are averaged over all pixels of the split; RMSE is the mean of per-image RMSEs,
which is how the paper's figures relate (its RMSE 0.1741 mm is below sqrt(MSE) = 0.2007 mm, as
the mean of square roots must be). A mask selects the pixels (all valid ones, or those shadowed
in at least one input view, where occlusion handling matters); images with no selected pixel
do not count towards the RMSE. MSE is in mm² (the paper's tables label it "mm").

Subsets (odmv.data.subsets): ``all`` valid pixels, ``shadowed`` (inside some projector's
footprint, unlit by one that covers it), ``unlit`` (lit by no projector), ``first_unlit``
(unlit by the first projector, lit by another) and ``first_shadowed`` (of those, inside the
first projector's footprint), all from the dataset's ground truth of every
projector, so models with different inputs compare; and the height bands ``h0_2``, ``h2_8`` and
``h8_up`` (mm above the base plane, the farthest valid depth of each image): where in height
the error lies (tall parts are what a net that regresses shape places too low); and the edge
band ``edge`` (pixels within 1 px of a depth jump over 1 mm between neighbouring pixels of the
ground truth: odmv.data.subsets.edge_band) and the rest, ``interior``. At 64 px the edge
band is a sixth of the pixels and carries most of every net's MAE, and its pixels mix two
surfaces; the interior is where a net must measure a surface, not place an edge.
"""

from __future__ import annotations

import torch
from torchmetrics import Metric

from odmv.classical.geometry import offset_from_depth
from odmv.data.subsets import MASKS, edge_band

#: height bands (mm above the base plane): name -> (lowest, highest)
HEIGHT_BANDS_MM = {"h0_2": (0.0, 2.0), "h2_8": (2.0, 8.0), "h8_up": (8.0, float("inf"))}
EDGE_BANDS = ("interior", "edge")
SUBSETS = ("all", *MASKS, *HEIGHT_BANDS_MM, *EDGE_BANDS)


def height_bands(depth_mm: torch.Tensor) -> dict[str, torch.Tensor]:
    """:data:`HEIGHT_BANDS_MM` masks (B x 1 x H x W, 0/1) of depth maps (mm, NaN: none)."""
    plane = depth_mm.nan_to_num(float("-inf")).amax((-2, -1), keepdim=True)
    height = plane - depth_mm  # NaN where there is no depth: in no band
    return {k: ((height >= lo) & (height < hi)).float() for k, (lo, hi) in HEIGHT_BANDS_MM.items()}


def edge_bands(depth_mm: torch.Tensor) -> dict[str, torch.Tensor]:
    """The ``interior`` and ``edge`` masks (B x 1 x H x W, 0/1) of depth maps (mm, NaN: none;
    a pixel without depth is in neither)."""
    valid = torch.isfinite(depth_mm)
    edge = edge_band(depth_mm)
    return {"interior": (valid & ~edge).float(), "edge": (valid & edge).float()}


def _masked_sums(pred_mm, target_mm, mask) -> tuple[torch.Tensor, ...]:
    """Per image (B, float64): sum of |error|, sum of error², number of masked pixels."""
    m = mask.to(torch.float64).flatten(1)
    err = (pred_mm.to(torch.float64) - target_mm.to(torch.float64)).flatten(1)
    err = torch.where(m > 0, err, 0.0) * m  # NaN targets (no ground truth) lie outside masks
    return err.abs().sum(1), (err**2).sum(1), m.sum(1)


def per_image_errors(
    pred_mm: torch.Tensor, target_mm: torch.Tensor, mask: torch.Tensor
) -> dict[str, torch.Tensor]:
    """Per image (B): MAE, MSE (mm²), RMSE over the masked pixels (NaN where none) and pixels."""
    abs_sum, sq_sum, n = _masked_sums(pred_mm, target_mm, mask)
    nan = torch.full_like(n, float("nan"))
    mae = torch.where(n > 0, abs_sum / n.clamp_min(1), nan)
    mse = torch.where(n > 0, sq_sum / n.clamp_min(1), nan)
    return {"mae_mm": mae, "mse_mm2": mse, "rmse_mm": mse.sqrt(), "pixels": n}


def subset_suffix(subset: str) -> str:
    """Metric-name suffix of a pixel subset: "" for all pixels, else "_<subset>"."""
    return "" if subset == "all" else f"_{subset}"


def per_image_subset_errors(
    pred_mm: torch.Tensor, target_mm: torch.Tensor, masks: dict[str, torch.Tensor]
) -> dict[str, torch.Tensor]:
    """:func:`per_image_errors` for every subset in ``masks``, keyed like the logged metrics
    (``mae_mm``, ``mae_mm_shadowed``, ``pixels_unlit``, ...): the columns of test_scenes.csv."""
    return {
        f"{name}{subset_suffix(subset)}": values
        for subset, mask in masks.items()
        for name, values in per_image_errors(pred_mm, target_mm, mask).items()
    }


def subset_results(stage: str, results: dict[str, dict[str, torch.Tensor]]) -> dict:
    """The logged metrics (``test/mae_mm_shadowed``, ``test/share_shadowed``, ...) from each
    subset's :meth:`DepthErrors.compute`; a subset's share is its part of the valid pixels."""
    valid = results["all"]["pixels"]
    out = {}
    for subset, values in results.items():
        suffix = subset_suffix(subset)
        for name, value in values.items():
            if name != "pixels":
                out[f"{stage}/{name}{suffix}"] = value
        if subset != "all":
            out[f"{stage}/share{suffix}"] = values["pixels"] / valid.clamp_min(1)
    return out


class DepthErrors(Metric):
    full_state_update = False

    def __init__(self):
        super().__init__()
        self.add_state("abs_sum", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("sq_sum", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("pixels", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("rmse_sum", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("images", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, pred_mm: torch.Tensor, target_mm: torch.Tensor, mask: torch.Tensor) -> None:
        """B x 1 x H x W predictions and targets in mm; mask B x 1 x H x W (nonzero = counted)."""
        abs_sum, sq, n = _masked_sums(pred_mm, target_mm, mask)
        self.abs_sum += abs_sum.sum()
        self.sq_sum += sq.sum()
        self.pixels += n.sum()
        has = n > 0
        self.rmse_sum += torch.sqrt(sq[has] / n[has]).sum()
        self.images += has.sum()

    def compute(self) -> dict[str, torch.Tensor]:
        """MAE, MSE, RMSE and the pixel count, over every process of a DDP run (torchmetrics
        sums the states only inside compute(), so the count is read here too)."""
        nan = torch.tensor(float("nan"), dtype=torch.float64, device=self.pixels.device)
        if self.pixels == 0:
            return {"mae_mm": nan, "mse_mm2": nan, "rmse_mm": nan, "pixels": self.pixels.clone()}
        return {
            "mae_mm": self.abs_sum / self.pixels,
            "mse_mm2": self.sq_sum / self.pixels,
            "rmse_mm": self.rmse_sum / self.images,
            "pixels": self.pixels.clone(),
        }


def wrong_orders(view_depth_mm, depth_mm, maps, lit) -> tuple[torch.Tensor, torch.Tensor]:
    """A phase head's fringe orders against the truth: the number of lit view pixels whose
    order is wrong (the view's depth, seen as its projector's offset, more than half a period
    from the true depth's) and the number of lit view pixels. ``view_depth_mm`` B x S x H x W,
    ``depth_mm`` B x 1 x H x W (NaN: none), ``maps`` the views' triangulation maps, ``lit`` B x
    S x H x W (nonzero: the view's projector lights the pixel)."""
    off = (offset_from_depth(view_depth_mm, maps) - offset_from_depth(depth_mm, maps)).abs()
    counted = (lit > 0.5) & torch.isfinite(depth_mm)
    wrong = counted & ~(off < maps[:, :, 1] / 2)  # NaN (an unlit view's depth) counts wrong
    return wrong.sum().double(), counted.sum().double()


class OrderErrors(Metric):
    """The share of lit view pixels whose fringe order a phase head got wrong."""

    full_state_update = False

    def __init__(self):
        super().__init__()
        self.add_state("wrong", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("lit", torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")

    def update(self, view_depth_mm, depth_mm, maps, lit) -> None:
        wrong, lit = wrong_orders(view_depth_mm, depth_mm, maps, lit)
        self.wrong += wrong
        self.lit += lit

    def compute(self) -> torch.Tensor:
        return self.wrong / self.lit if self.lit > 0 else self.wrong.new_tensor(float("nan"))
