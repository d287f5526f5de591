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
the error lies (tall parts are what a net that regresses shape places too low).
"""

from __future__ import annotations

import torch
from torchmetrics import Metric

from odmv.data.subsets import MASKS

#: height bands (mm above the base plane): name -> (lowest, highest)
HEIGHT_BANDS_MM = {"h0_2": (0.0, 2.0), "h2_8": (2.0, 8.0), "h8_up": (8.0, float("inf"))}
SUBSETS = ("all", *MASKS, *HEIGHT_BANDS_MM)


def height_bands(depth_mm: torch.Tensor) -> dict[str, torch.Tensor]:
    """:data:`HEIGHT_BANDS_MM` masks (B x 1 x H x W, 0/1) of depth maps (mm, NaN: none)."""
    plane = depth_mm.nan_to_num(float("-inf")).amax((-2, -1), keepdim=True)
    height = plane - depth_mm  # NaN where there is no depth: in no band
    return {k: ((height >= lo) & (height < hi)).float() for k, (lo, hi) in HEIGHT_BANDS_MM.items()}


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
