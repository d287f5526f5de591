"""An exponential moving average of the weights (``ema=DECAY``; beyond the paper).

Lightning's EMA callback validates the averaged weights and saves them as a checkpoint's
``state_dict`` (the raw ones beside them, for resuming), so the best checkpoint is the best
average and evaluation, prediction and export load it unchanged. One change: its checkpoint
loading puts the raw weights back whenever it holds an average, which after ``fit`` includes the
same trainer's ``test`` of the best checkpoint; that test has to score the average it was
chosen by, so outside fitting the loaded ``state_dict`` stands.
"""

from __future__ import annotations

from lightning.pytorch.callbacks import EMAWeightAveraging
from lightning.pytorch.trainer.states import TrainerFn


class WeightEMA(EMAWeightAveraging):
    """EMA of every parameter and buffer, updated after each optimizer step with weight
    ``1 - decay`` for the new weights (a memory of about ``1 / (1 - decay)`` steps)."""

    def __init__(self, decay: float):
        if not 0.0 < decay < 1.0:
            raise ValueError(f"ema: the decay must lie in (0, 1), got {decay}")
        super().__init__(decay=decay)

    def on_load_checkpoint(self, trainer, pl_module, checkpoint) -> None:
        if trainer.state.fn == TrainerFn.FITTING:
            super().on_load_checkpoint(trainer, pl_module, checkpoint)
