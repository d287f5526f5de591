"""One LightningModule for every net: composite loss, mm metrics, optimizer, TensorBoard images.

Hyperparameters hold plain data only (the net's config dict, loss weights, normalization,
optimizer settings), so checkpoints load with torch's ``weights_only`` and a net can be rebuilt
from a checkpoint alone (:func:`load_module`).
"""

from __future__ import annotations

import random
import time
from dataclasses import asdict
from pathlib import Path

import hydra
import hydra.errors
import lightning as L
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.plugins.precision import MixedPrecision
from lightning.pytorch.utilities import rank_zero_only
from omegaconf import OmegaConf

from odmv.data.normalize import Normalization
from odmv.data.subsets import MASKS
from odmv.io.atomic import write_csv, write_npz
from odmv.io.runfolder import PREDICTIONS, SCENES_CSV, recorded_dataset
from odmv.models.blocks import split_availability
from odmv.models.phase import check_head, fuse, reads_maps
from odmv.training.checkpoint import CheckpointError, check_weights, read_checkpoint
from odmv.training.configs import adapt_settings, data_config, distill_settings, run_summary
from odmv.training.consistency import ConsistencySettings, consistency_loss
from odmv.training.distill import DistillSettings, distill_terms
from odmv.training.losses import LossWeights, composite_loss, depth_loss
from odmv.training.metrics import (
    SUBSETS,
    DepthErrors,
    OrderErrors,
    edge_bands,
    height_bands,
    per_image_subset_errors,
    subset_results,
)

#: the paper's optimizer and schedule (conf/optimizer/adam.yaml, conf/scheduler/cosine_restarts)
OPTIMIZER = "torch.optim.Adam"
SCHEDULER = "torch.optim.lr_scheduler.CosineAnnealingWarmRestarts"


def make_optimizer(params, cfg: dict | None):
    """The optimizer config ``cfg`` names (``_target_`` and its arguments; Adam where it names
    none, as in checkpoints from before optimizers were configs) over ``params``."""
    named = {"_target_": OPTIMIZER, **(cfg or {"lr": 1e-4})}
    return hydra.utils.instantiate(named | {"_partial_": True})(params)


class NonFiniteLossError(ValueError):
    """The training loss became NaN or infinite; training stops."""


def rng_states() -> dict:
    """The random generators' states as plain data and tensors (a weights_only checkpoint)."""
    kind, keys, pos, has_gauss, gauss = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    states = {
        "torch": torch.get_rng_state(),
        "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos, has_gauss, gauss],
        "python": [version, list(internal), gauss_next],
    }
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        states["cuda"] = torch.cuda.get_rng_state_all()
    return states


def set_rng_states(states: dict) -> None:
    torch.set_rng_state(states["torch"])
    kind, keys, pos, has_gauss, gauss = states["numpy"]
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, gauss))
    version, internal, gauss_next = states["python"]
    random.setstate((version, tuple(internal), gauss_next))
    if "cuda" in states and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])


def build_net(net_cfg: dict) -> torch.nn.Module:
    for key in ("base_width", "full_width"):
        width = net_cfg.get(key)
        if width is not None and (not isinstance(width, int) or width < 1):
            raise ValueError(f"model.net.{key}: {width!r}; a positive channel count")
    return hydra.utils.instantiate(net_cfg, _convert_="all")


class FPPModule(L.LightningModule):
    def __init__(
        self,
        net_cfg: dict,
        norm: dict | None = None,
        views: list[str] | None = None,
        loss: dict | None = None,
        optimizer: dict | None = None,
        scheduler: dict | None = None,
        log_images: int = 2,
        data_cfg: dict | None = None,
        input_spec: dict | None = None,
        run_info: dict | None = None,
        compile: str | None = None,
        adapt: dict | None = None,
        distill: dict | None = None,
    ):
        super().__init__()
        # logged by on_fit_start once the data has resolved the views and normalization
        self.save_hyperparameters(logger=False)
        self.net = build_net(net_cfg)
        # a head that reads the rig's maps (head=phase) fuses its depth through them
        self.phase_head = reads_maps(net_cfg.get("head"))
        # torch.compile's wrapper of the net, kept off the module tree: the checkpoint holds
        # the plain net's weights under their own names, loadable with or without compiling
        object.__setattr__(
            self, "_compiled", torch.compile(self.net, mode=compile) if compile else None
        )
        self.norm = Normalization(**norm) if norm else None
        self.weights = LossWeights(**(loss or {}))
        # label-free adaptation (adapt=true): the consistency loss and its trust region around
        # the net it started from (``base``: that net's checkpoint), instead of the composite
        # loss; there is no ground truth, so no metric is computed
        self.adapt = ConsistencySettings.of(adapt) if adapt else None
        object.__setattr__(self, "_base", None)  # that net, frozen, off the module tree
        # adaptation.target=classical: {scene id: depth (mm, NaN where none)} that phase
        # shifting reconstructs from the user's sequences (set by the training app)
        self.classical_mm: dict | None = None
        # distillation (distill_from=RUN): the teacher's outputs as targets beside the truth
        self.distill = DistillSettings.of(distill) if distill else None
        object.__setattr__(self, "_teacher_net", None)  # frozen, off the module tree
        self.metrics = torch.nn.ModuleDict(
            {f"{stage}_{subset}": DepthErrors() for stage in ("val", "test") for subset in SUBSETS}
        )
        # head=phase: the share of lit view pixels whose fringe order is wrong
        self.order_errors = torch.nn.ModuleDict(
            {stage: OrderErrors() for stage in ("val", "test")} if self.phase_head else {}
        )
        # where a test writes its per-scene metrics and predictions (set by the apps)
        self.test_dir: Path | None = None
        self._scene_rows: list[dict] = []
        self._predictions: dict[str, list] = {}
        # training time across resumes: what the checkpoint fitted from had spent, plus this fit
        self._seconds_before, self._fit_started = 0.0, None

    @classmethod
    def from_config(cls, cfg, norm: dict | None = None, views: list[str] | None = None):
        """The module a composed train config trains (its net, loss, optimizer, schedule,
        fine-tune and teacher); the normalization and views come from the data at setup
        unless given."""
        return cls(
            net_cfg=OmegaConf.to_container(cfg.model.net, resolve=True),
            norm=norm,
            views=views,
            loss=OmegaConf.to_container(cfg.loss, resolve=True),
            optimizer=OmegaConf.to_container(cfg.optimizer, resolve=True),
            scheduler=OmegaConf.to_container(cfg.scheduler, resolve=True),
            log_images=cfg.log_images,
            data_cfg=data_config(cfg),
            run_info=run_summary(cfg),
            compile=cfg.get("compile"),
            adapt=adapt_settings(cfg),
            distill=distill_settings(cfg),
        )

    def setup(self, stage: str) -> None:
        """Take units and views from the data module; they are saved with the checkpoint."""
        dm = getattr(self.trainer, "datamodule", None)
        if dm is not None and dm.norm is not None:
            if self.norm is not None and self.norm != dm.norm:
                raise ValueError(
                    f"checkpoint normalization {self.norm} differs from the data's "
                    f"{dm.norm}; evaluate on data made with the same settings"
                )
            self.norm = dm.norm
            self.hparams["norm"] = dm.norm.to_dict()
            self.hparams["views"] = list(dm.spec.views)
            spec = dm.spec  # what predict needs to rebuild the net's input from images
            self.hparams["input_spec"] = {
                "reference": spec.reference,
                "availability": dm.view_dropout is not None,  # odmv.data.views
                "period_px": spec.period_px,
                "step": spec.step,
                "n_steps": spec.n_steps,
                "quantity": dm.manifest.quantity,  # what the depth maps hold: depth or height
                "calibration": spec.calibration,  # the batches carry the triangulation maps
                "head": check_head(self.hparams.net_cfg.get("head"))[0],  # what the net reads
            }
            # one input at the data's size: the model summary then counts FLOPs per sample
            ds = next(iter(dm.datasets.values()), None)
            if ds is not None and len(ds):
                sample = batched(ds[0])
                x = torch.zeros_like(net_input(sample))
                calibration = sample.get("calibration")
                self.example_input_array = x if calibration is None else (x, calibration)

    def _start_net(self) -> FPPModule | None:
        """The frozen net adaptation started from (loaded at first use)."""
        base = (self.hparams.adapt or {}).get("base")
        if self._base is None and base and self.adapt.anchor:
            net = load_module(base).eval().requires_grad_(False)
            object.__setattr__(self, "_base", net)
        if self._base is not None:
            self._base.to(self.device)
        return self._base

    def adapt_terms(self, batch: dict, out: dict) -> dict[str, torch.Tensor]:
        """Label-free adaptation's loss terms: ``consistency`` (odmv.training.consistency) and
        ``phase_rad`` (its weighted RMS phase error), or with ``target=classical`` the run's
        depth loss against the classical depth (``classical``) and the share of pixels that
        have one (``covered``); ``change_mm`` (the mean absolute change from the starting
        net) and their sum ``loss``, the fit + anchor x change."""
        depth_mm = self.depth_mm(out)
        if self.adapt.target == "classical":
            target = self._classical_target(batch["scene_id"], depth_mm)
            fit = depth_loss(out["depth"], self.norm.depth(target), self.weights)["loss"]
            covered = torch.isfinite(target).float().mean()
            terms = {"classical": fit, "covered": covered, "loss": fit}
            terms["classical_mae_mm"] = mae_where_known(depth_mm, target)
        else:
            linear = self.norm.intensity(batch["fringes"].float())
            fit = consistency_loss(
                depth_mm, linear, batch["calibration"], self.adapt, batch.get("available")
            )
            terms = {"consistency": fit["loss"], "phase_rad": fit["phase_rad"]}
            terms["loss"] = fit["loss"]
        start = self._start_net()
        if start is not None:
            with torch.no_grad():
                start_mm = start.depth_mm(start.run(batch))
            terms["change_mm"] = (depth_mm - start_mm).abs().mean()
            terms["loss"] = terms["loss"] + self.adapt.anchor * terms["change_mm"]
        return terms

    def _classical_target(self, scene_ids, like: torch.Tensor) -> torch.Tensor:
        """The classical depth (mm, NaN where none) of a batch's scenes, shaped like ``like``."""
        if self.classical_mm is None:
            raise RuntimeError("adaptation.target=classical: no classical depth was decoded")
        return torch.stack([self.classical_mm[s] for s in scene_ids])[:, None].to(like)

    def _teacher(self) -> FPPModule:
        """The frozen teacher of distillation (loaded at first use), checked to read the same
        input and depth units as this net."""
        if self._teacher_net is None:
            teacher = load_module(self.distill.teacher).eval().requires_grad_(False)
            hp, mine = teacher.hparams, self.hparams
            for what, theirs, ours in (
                ("views", hp.views, mine.views),
                ("normalization", hp.norm, mine.norm),
                ("input", _input_keys(hp.input_spec), _input_keys(mine.input_spec)),
            ):
                if theirs != ours:
                    raise ValueError(
                        f"distill_from: {self.distill.teacher}: the teacher's {what} "
                        f"({theirs}) differ from this run's ({ours})"
                    )
            if teacher.phase_head and not self.phase_head:
                raise ValueError(
                    f"distill_from: {self.distill.teacher}: the teacher has the phase head; "
                    "train the student with head=phase (its batches then carry the calibration)"
                )
            object.__setattr__(self, "_teacher_net", teacher)
        return self._teacher_net.to(self.device)

    def forward(self, inputs: torch.Tensor, calibration: torch.Tensor | None = None) -> dict:
        """``inputs``: the net's input, i.e. a batch's ``inputs`` (fringes plus the reference
        phase) when the data has them, else its normalized ``fringes``. ``calibration``: the
        batch's triangulation maps (B x S x 6 x H x W, odmv.classical.geometry), which a net
        with the
        phase head needs to turn its views' phase into the fused ``depth``."""
        net = self.net if self._compiled is None else self._compiled
        out = net(inputs)
        if not self.phase_head:
            return out
        if calibration is None:
            raise ValueError("head=phase: the net needs the rig's calibration maps with its input")
        available = None
        if (self.hparams.input_spec or {}).get("availability"):
            available = split_availability(inputs, calibration.shape[1])[1]
        return fuse(out, calibration, self.norm, available)

    def run(self, batch: dict) -> dict:
        """The net's outputs for a batch (or one sample with a batch axis added)."""
        return self(net_input(batch), batch.get("calibration"))

    # ---------------------------------------------------------------- steps
    def training_step(self, batch, _):
        replay = batch.get("replay")  # adaptation's batch of the twin the net was trained on
        batch = batch.get("own", batch)
        out = self.run(batch)
        terms = (
            self.adapt_terms(batch, out) if self.adapt else composite_loss(out, batch, self.weights)
        )
        if self.distill is not None:
            with torch.no_grad():
                teacher_out = self._teacher().run(batch)
            taught = distill_terms(out, teacher_out, self.distill)
            terms |= {k: v for k, v in taught.items() if k != "loss"}
            terms["loss"] = terms["loss"] + taught["loss"]
        if replay is not None:
            terms["replay"] = composite_loss(self.run(replay), replay, self.weights)["loss"]
            terms["loss"] = terms["loss"] + self.adapt.replay * terms["replay"]
        if not torch.isfinite(terms["loss"]):  # stop: every later step and metric would be NaN
            bad = [k for k, v in terms.items() if not torch.isfinite(v)]
            raise NonFiniteLossError(
                f"train/loss: {float(terms['loss'])} at epoch {self.current_epoch}, step "
                f"{self.global_step} (non-finite terms: {', '.join(bad)}; scenes "
                f"{', '.join(batch['scene_id'])})"
            )
        bs = batch["fringes"].shape[0]
        self.log("train/loss", terms["loss"], prog_bar=True, batch_size=bs)
        # the epoch mean draws a curve even when an epoch is shorter than log_every_n_steps
        self.log(
            "train/loss_epoch",
            terms["loss"],
            on_step=False,
            on_epoch=True,
            sync_dist=True,
            batch_size=bs,
        )
        for k, v in terms.items():
            if k != "loss":
                self.log(f"train/loss_{k}", v, batch_size=bs)
        return terms["loss"]

    def depth_mm(self, out: dict) -> torch.Tensor:
        """The net's depth in mm, converted in float32 whatever the autocast precision."""
        with torch.autocast(out["depth"].device.type, enabled=False):
            return self.norm.depth_mm(out["depth"].float())

    def _evaluate(self, batch, stage: str) -> tuple[dict, torch.Tensor, dict]:
        """Loss and metrics of one batch; returns the output, the depth in mm and the masks."""
        out = self.run(batch)
        bs = batch["fringes"].shape[0]
        pred_mm = self.depth_mm(out)
        masks = subset_masks(batch)
        if self.adapt:  # no ground truth: the label-free terms are the measure
            for k, v in self.adapt_terms(batch, out).items():
                self.log(f"{stage}/{k}", v, batch_size=bs, sync_dist=True)
            return out, pred_mm, masks
        terms = composite_loss(out, batch, self.weights)
        for subset, mask in masks.items():
            self.metrics[f"{stage}_{subset}"].update(pred_mm, batch["depth_mm"], mask)
        if stage in self.order_errors:
            self.order_errors[stage].update(
                out["view_depth_mm"], batch["depth_mm"], batch["calibration"], batch["lit"]
            )
        self.log(f"{stage}/loss", terms["loss"], batch_size=bs, sync_dist=True)
        return out, pred_mm, masks

    def validation_step(self, batch, batch_idx):
        out, _, _ = self._evaluate(batch, "val")
        if batch_idx == 0 and self.hparams.log_images:
            self._log_images(batch, out)

    def test_step(self, batch, _):
        _, pred_mm, masks = self._evaluate(batch, "test")
        if self.test_dir is None:
            return
        if self.adapt:  # no ground truth: the depth, beside the classical target where fitted
            self._keep_label_free(batch, pred_mm)
            return
        per = per_image_subset_errors(pred_mm, batch["depth_mm"], masks)
        for i, sid in enumerate(batch["scene_id"]):
            row = {"scene": sid, "family": batch["family"][i]}
            self._scene_rows.append(row | {k: float(v[i]) for k, v in per.items()})
        for key, value in (
            ("scene_id", list(batch["scene_id"])),
            ("pred_mm", pred_mm[:, 0].float().cpu().numpy()),
            ("depth_mm", batch["depth_mm"][:, 0].cpu().numpy()),
        ):
            self._predictions.setdefault(key, []).append(value)

    def _keep_label_free(self, batch, pred_mm: torch.Tensor) -> None:
        """An adapted net's test scenes kept for its page: its depth (mm) and, with the classical
        target, the classical depth it was fitted to and its MAE against it per scene."""
        kept = {"scene_id": list(batch["scene_id"]), "pred_mm": pred_mm[:, 0].float().cpu().numpy()}
        classical = None
        if self.adapt.target == "classical":
            classical = self._classical_target(batch["scene_id"], pred_mm)
            kept["classical_mm"] = classical[:, 0].float().cpu().numpy()
        for i, sid in enumerate(batch["scene_id"]):
            row = {"scene": sid}
            if classical is not None:
                row |= {"classical_mae_mm": float(mae_where_known(pred_mm[i], classical[i])),
                        "covered": float(torch.isfinite(classical[i]).float().mean())}  # fmt: skip
            self._scene_rows.append(row)
        for key, value in kept.items():
            self._predictions.setdefault(key, []).append(value)

    def _log_metrics(self, stage: str) -> None:
        if self.adapt:
            return
        # compute() sums over ranks, so every rank logs the same values (sync_dist keeps them)
        results = {subset: self.metrics[f"{stage}_{subset}"].compute() for subset in SUBSETS}
        for name, value in subset_results(stage, results).items():
            self.log(name, value.float(), sync_dist=True)
        for subset in SUBSETS:
            self.metrics[f"{stage}_{subset}"].reset()
        if stage in self.order_errors:
            self.log(f"{stage}/order_wrong", self.order_errors[stage].compute().float())
            self.order_errors[stage].reset()

    def on_validation_epoch_end(self):
        self._log_metrics("val")

    def on_test_epoch_start(self):
        self._scene_rows, self._predictions = [], {}

    def on_test_epoch_end(self):
        self._log_metrics("test")
        if self.test_dir is not None:
            rows, predictions = self._scene_rows, self._predictions
            if self.trainer.world_size > 1:  # every rank tested its share of the scenes
                rows, predictions = _gather(rows), _gather_lists(predictions)
            if rows:
                write_test_outputs(Path(self.test_dir), rows, predictions)

    # ---------------------------------------------------------------- optimisation
    def configure_optimizers(self):
        opt = make_optimizer(self.parameters(), self.hparams.optimizer)
        # a checkpoint from before schedules were configs names no _target_: cosine
        sch_cfg = {"_target_": SCHEDULER, **(self.hparams.scheduler or {"T_0": 10})}
        interval = sch_cfg.pop("interval", "epoch")
        sched = hydra.utils.instantiate(sch_cfg | {"_partial_": True})(opt)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": interval}}

    def configure_gradient_clipping(
        self, optimizer, gradient_clip_val=None, gradient_clip_algorithm=None
    ):
        plugin = self.trainer.precision_plugin
        if gradient_clip_val and isinstance(plugin, MixedPrecision) and plugin.scaler is None:
            # bf16-mixed scales no gradient, so clipping before a fused Adam step is right;
            # Lightning's plugin refuses every fused optimizer, as float16's scaler needs it to
            params = list(plugin.main_params(optimizer))
            if gradient_clip_algorithm == "value":
                torch.nn.utils.clip_grad_value_(params, gradient_clip_val)
            else:
                torch.nn.utils.clip_grad_norm_(params, gradient_clip_val)
            return
        super().configure_gradient_clipping(optimizer, gradient_clip_val, gradient_clip_algorithm)

    # ---------------------------------------------------------------- TensorBoard
    @rank_zero_only
    def _log_images(self, batch, out) -> None:
        tb = next(
            (lg.experiment for lg in self.loggers if hasattr(lg.experiment, "add_image")), None
        )
        if tb is None:
            return
        n = min(self.hparams.log_images, batch["fringes"].shape[0])
        gt = batch["depth_mm"][:n]
        pred = self.depth_mm(out)[:n].detach()
        known = gt[torch.isfinite(gt)]  # NaN: no ground truth, drawn black
        lo, hi = (
            (known.amin(), known.amax()) if known.numel() else (gt.new_tensor(0), gt.new_tensor(1))
        )
        gt = gt.nan_to_num(float(lo))
        step = self.global_step

        def grid(x):  # N x C x H x W in [0, 1] -> 1 x NH x CW: samples in rows, channels across
            k, c, h, w = x.shape
            return x.permute(0, 2, 1, 3).reshape(k * h, c * w)[None].clamp(0, 1).float().cpu()

        tb.add_image("val/fringes", grid((batch["fringes"][:n] + 1) / 2), step)
        tb.add_image("val/depth_gt", grid((gt - lo) / (hi - lo + 1e-9)), step)
        tb.add_image("val/depth_pred", grid((pred - lo) / (hi - lo + 1e-9)), step)
        tb.add_image("val/abs_error_0-1mm", grid((pred - gt).abs()), step)
        if "occlusion" in out:
            tb.add_image("val/ocd_masks", grid(out["occlusion"][0][:n, 0].detach()), step)
        if "views" in out:
            tb.add_image("val/views_reconstructed", grid((out["views"][:n].detach() + 1) / 2), step)

    def train_seconds(self) -> float:
        """Seconds of fitting that led to these weights, over every resume."""
        now = 0.0 if self._fit_started is None else time.perf_counter() - self._fit_started
        return self._seconds_before + now

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["train_seconds"] = self.train_seconds()
        checkpoint["rng"] = rng_states()

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        self._seconds_before = float(checkpoint.get("train_seconds", 0.0))
        if checkpoint.get("rng") is not None and self._trainer is not None:
            # a resumed fit: the generators as the interrupted run left them, before the
            # loader draws its first shuffle (Lightning creates that iterator ahead of the epoch
            # hooks), so the resumed run sees the batches of the uninterrupted one
            set_rng_states(checkpoint["rng"])

    def on_fit_start(self):
        """Key settings with the metrics they led to, for TensorBoard's HPARAMS tab (which shows
        the last logged value of each metric) and the loggers' hparams.yaml; starts the clock
        of :meth:`train_seconds`."""
        self._fit_started = time.perf_counter()
        if self.distill is not None:  # a teacher that cannot teach this net stops the run now
            self._teacher()
        params = {
            **(self.hparams.run_info or {}),
            "views": ",".join(self.hparams.views or []),
            "parameters": sum(p.numel() for p in self.net.parameters()),
            **{f"norm/{k}": v for k, v in (self.hparams.norm or {}).items()},
            **{f"loss/{k}": str(v) for k, v in asdict(self.weights).items()},
        }
        params = {k: v for k, v in params.items() if v is not None}
        for lg in self.loggers:
            lg.log_hyperparams(params)
            if isinstance(lg, TensorBoardLogger):
                _add_hparams_session(lg, params)


HPARAM_METRICS = ("val/mae_mm", "val/mae_mm_shadowed", "test/mae_mm", "test/mae_mm_shadowed")


@rank_zero_only
def _add_hparams_session(logger: TensorBoardLogger, params: dict) -> None:
    """Write the HPARAMS session without logging placeholder metric values (Lightning's own
    call would log them as a first point of each curve)."""
    from torch.utils.tensorboard.summary import hparams

    writer = logger.experiment._get_file_writer()
    for summary in hparams(params, dict.fromkeys(HPARAM_METRICS, 0.0)):
        writer.add_summary(summary)


def _input_keys(spec: dict | None) -> dict:
    """What decides the net's input tensor (a teacher must read the student's)."""
    spec = spec or {}
    return {k: spec.get(k) for k in ("reference", "availability", "period_px", "quantity")}


def net_input(batch: dict) -> torch.Tensor:
    """The tensor a net takes from a batch or sample (see :meth:`FPPModule.forward`)."""
    return batch["inputs"] if "inputs" in batch else batch["fringes"]


def batched(sample: dict) -> dict:
    """One sample as a batch of one (tensors get a batch axis, other values a list)."""
    return {k: v[None] if torch.is_tensor(v) else [v] for k, v in sample.items()}


def subset_masks(batch: dict) -> dict[str, torch.Tensor]:
    """Metric pixel masks (B x 1 x H x W) from the batch's ground truth: odmv.data.subsets, and
    the height bands and edge bands of odmv.training.metrics."""
    valid = batch["valid"]
    masks = {"all": valid} | {k: batch[k] * valid for k in MASKS}
    edges = {k: m * valid for k, m in edge_bands(batch["depth_mm"]).items()}
    return masks | height_bands(batch["depth_mm"]) | edges


def _gather(items: list) -> list:
    """Every rank's list, concatenated in rank order (picklable items)."""
    parts = [None] * torch.distributed.get_world_size()
    torch.distributed.all_gather_object(parts, items)
    return [x for part in parts for x in part]


def _gather_lists(lists: dict[str, list]) -> dict[str, list]:
    return {k: _gather(lists.get(k, [])) for k in ("scene_id", "pred_mm", "depth_mm")}


def write_scene_rows(folder: Path, rows: list[dict]) -> None:
    """Per-scene metrics as ``test_scenes.csv``, atomically, in scene order."""
    rows = sorted({r["scene"]: r for r in rows}.values(), key=lambda r: r["scene"])
    write_csv(folder / SCENES_CSV, rows)


def mae_where_known(pred_mm: torch.Tensor, target_mm: torch.Tensor) -> torch.Tensor:
    """Mean |pred - target| (mm) over the pixels where the target is finite; NaN where none."""
    known = torch.isfinite(target_mm)
    return (pred_mm - target_mm)[known].abs().mean()  # an empty mean is NaN


@rank_zero_only
def write_test_outputs(folder: Path, rows: list[dict], predictions: dict[str, list]) -> None:
    """Per-scene metrics (CSV) and the test predictions in mm (npz), each written atomically,
    in scene order (the same files however many processes tested)."""
    folder.mkdir(parents=True, exist_ok=True)
    write_scene_rows(folder, rows)
    ids = np.array([s for chunk in predictions["scene_id"] for s in chunk])
    _, order = np.unique(ids, return_index=True)  # scene order, each scene once
    arrays = {"scene_id": ids[order]}
    for key in predictions.keys() - {"scene_id"}:  # depth_mm, or classical_mm of an adaptation
        arrays[key] = np.concatenate(predictions[key]).astype(np.float32)[order]
    write_npz(folder / PREDICTIONS, arrays)


def load_module(ckpt_path: str | Path) -> FPPModule:
    """Rebuild a trained module (on the CPU) from its checkpoint alone; a missing, unreadable,
    foreign or inconsistent file raises CheckpointError naming it. Its dataset, where saved
    relative to the training's working folder, is looked for from the checkpoint's folder too
    (odmv.io.runfolder.recorded_dataset), so evaluate and export find it from anywhere."""
    ckpt = read_checkpoint(ckpt_path)
    try:
        # evaluated, predicted and exported eagerly and as a net of its own, however it was
        # trained (an adapted net's settings stay in its hyperparameters)
        hp = ckpt["hyper_parameters"]
        module = FPPModule(**(hp | {"compile": None, "adapt": None, "distill": None}))
        module.hparams["adapt"], module.hparams["distill"] = hp.get("adapt"), hp.get("distill")
    except (TypeError, ValueError, hydra.errors.InstantiationException) as e:
        raise CheckpointError(f"{ckpt_path}: its net settings do not build a net ({e})") from None
    check_weights(ckpt_path, ckpt["state_dict"], module.state_dict())
    module.load_state_dict(ckpt["state_dict"])
    data = module.hparams.get("data_cfg")
    if data and data.get("root"):  # saved as the training's command line gave it
        data["root"] = str(recorded_dataset({"dataset": data["root"]}, Path(ckpt_path).parent))
    return module
