"""Knowledge distillation (beyond the paper; ``distill_from=RUN``): a trained net (the teacher,
frozen) teaches another (the student, e.g. the light ODMV-Net) beside the ground truth.

The teacher runs on every training batch (no cache: the mini protocol's training samples draw
phase steps and flips anew each epoch, so a cache would hold outputs of inputs the student
never sees again). Its depth is a dense target free of the ground truth's label noise at part
edges; where both nets have the phase head, its views' wrapped phase and its blend weights
teach the student's per-view decoding and confidence too.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass(frozen=True)
class DistillSettings:
    teacher: str  # the teacher's checkpoint
    depth: float = 1.0  # L1 to the teacher's depth (net units)
    phase: float = 1.0  # squared error to the teacher's views' (sin, cos); phase heads only
    confidence: float = 1.0  # cross-entropy to the teacher's blend weights; phase heads only

    @classmethod
    def of(cls, d: dict) -> DistillSettings:
        return cls(**{k: d[k] for k in ("teacher", "depth", "phase", "confidence") if k in d})


def distill_terms(student: dict, teacher: dict, s: DistillSettings) -> dict[str, torch.Tensor]:
    """The distillation terms (``distill_depth``, and with two phase heads ``distill_phase``
    and ``distill_confidence``) and their weighted sum ``loss``, from the two nets' outputs."""
    with torch.autocast(student["depth"].device.type, enabled=False):
        terms = {"distill_depth": F.l1_loss(student["depth"].float(), teacher["depth"].float())}
        loss = s.depth * terms["distill_depth"]
        if "weights" in student and "weights" in teacher:
            terms["distill_phase"] = F.mse_loss(student["phase"].float(), teacher["phase"].float())
            log_p = torch.log_softmax(student["confidence"].float(), 1)
            terms["distill_confidence"] = -(teacher["weights"].float() * log_p).sum(1).mean()
            loss = loss + s.phase * terms["distill_phase"]
            loss = loss + s.confidence * terms["distill_confidence"]
    return terms | {"loss": loss}
