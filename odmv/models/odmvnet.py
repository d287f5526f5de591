"""ODMV-Net: multi-view fringe images -> depth, with occlusion detection and view reconstruction.

Input B x S x H x W normalized fringes (S views, H and W multiples of 16). Inside, features form
a 3D volume B x C x S x h x w whose view axis is the depth axis of the 3D convolutions.

Choices where the paper (Sec. II.A, Figs. 1-2) is silent, as implemented here:
- Residual View Encoder: the per-view 2D convolutions share weights (the paper's "hard
  parameter sharing"; the net then takes any S and any view order); two anisotropic (3,1,1)
  convolutions mix views, and a residual connection adds the stacked per-view features back.
  With ``rve`` off, a plain 3x3x3 conv stem. ``stem_stride`` 1 (default) keeps the whole 3D
  backbone at full resolution. ``stem_stride`` 2 (the paper's "strided convolutions"; 4x less
  backbone compute) runs the backbone at half resolution: the stem keeps a full-resolution
  feature (``full_width`` channels, default half the base width), a transposed (1,2,2)
  convolution brings the last decoder stage back to full resolution, one 3D block merges it
  with that feature, and Main is fused and regressed there; Aux1 and Aux2 then sit on the
  decoder's 1/2 and 1/4 stages, the paper's scales. The plain stem (Table I rows without
  RVE) strides the same way, so the rows differ in modules, not in resolution. ``stem_stride``
  4 (the light net, beyond the paper) runs the backbone at quarter resolution the same way
  (a 7 px strided stem kernel, a (1,4,4) transposed convolution back), Aux1 and Aux2 on the
  1/4 and 1/8 stages; with ``levels`` 3 its bottleneck sits at 1/32, so 480 px still divides.
- Backbone: four encoder stages (``levels``; full, 1/2, 1/4, 1/8 resolution) of ``blocks`` 3D
  residual blocks, max-pooling (1,2,2) between them, a bottleneck at 1/16, and a mirrored
  decoder with transposed (1,2,2) convolutions. Without ``residual``, stages are vanilla
  double conv-BN-ReLU blocks.
- 3D ASPP at the bottleneck replaces the second residual block (rates 2, 4, 6 in space, 1 across
  views, plus image pooling), as Table I's note says ASPP replaces intermediate convolutions.
- Attention gates (Oktay et al.) on every skip, gated by the coarser decoder features.
- OCD: one lightweight depthwise-separable head per skip scale predicts a soft per-view mask
  (B x 1 x S x h x w) from the encoder features and multiplies that skip before it is gated.
- OAF at Main (1/1), Aux1 (1/2) and Aux2 (1/4): channel-view and spatial attention, then a
  softmax-over-views blend in which the OCD mask lowers the weight of views it finds occluded
  (``fusion_bound`` limits the attention's share of that blend, beyond the paper);
  scale-specific 2D regression heads follow. Without ``ocd_oaf``: plain mean over views.
- SSVR: a 3D conv head on the final decoder stage gives one map per view through a Tanh.
- Deep supervision (Main/Aux1/Aux2) is part of every ablation row: Table I varies modules, not
  the training protocol.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint

from odmv.models.blocks import (
    ASPP3d,
    AttentionGate3d,
    OcclusionAwareFusion,
    OcclusionDetector,
    RegressionHead,
    ResBlock3d,
    conv_bn_act,
    set_gate_init,
    set_memory_format,
    set_norm,
    set_separable,
    set_view_padding,
    split_availability,
    stage3d,
    view_mean,
)
from odmv.models.phase import PhaseHead3d, check_head

LEVELS = 4  # encoder stages by default; the bottleneck sits at 1 / (stem_stride * 2**levels)
STEM_STRIDES = (1, 2, 4)


SWITCHES = ("residual", "attention_gates", "aspp", "rve", "ocd_oaf", "ssvr")


class TableIRow(NamedTuple):
    """A row of the paper's Table I: ``ablation=KEY`` trains it (a config option registered
    from this table by odmv.config), the report labels it and sets the paper's figures beside
    it, the ablation sweep runs every row."""

    key: str
    label: str
    adds: tuple[str, ...]  # the switches this row adds to the previous one
    paper: tuple[float, float, float]  # the paper's MAE (mm), MSE (mm^2), RMSE (mm) at S = 4


#: Table I's cumulative module rows, in the paper's order: the one place they are declared
TABLE_I = (
    TableIRow("baseline", "Baseline (vanilla 3D U-Net)", (), (0.0926, 0.1337, 0.3442)),
    TableIRow("rb_ag", "+RB&AG", ("residual", "attention_gates"), (0.0463, 0.0440, 0.1840)),
    TableIRow("aspp", "+ASPP", ("aspp",), (0.0451, 0.0432, 0.1778)),
    TableIRow("rve", "+RVE", ("rve",), (0.0461, 0.0427, 0.1776)),
    TableIRow("ocd_oaf", "+OCD&OAF", ("ocd_oaf",), (0.0452, 0.0411, 0.1747)),
    TableIRow("multitask", "+Multi-task (ODMV-Net)", ("ssvr",), (0.0447, 0.0403, 0.1741)),
)


def _rows() -> dict[str, dict[str, bool]]:
    rows, on = {}, set()
    for row in TABLE_I:
        on |= set(row.adds)
        rows[row.key] = {k: k in on for k in SWITCHES}
    return rows


#: Table I rows: switch settings per row, each row adding to the previous one.
ABLATION_ROWS: dict[str, dict[str, bool]] = _rows()


def _stem_kernel(stride: int) -> int:
    """The strided stem layer's kernel: 2 x stride - 1 wide, so every pixel reaches the
    coarser grid (3 at stride 1 and 2, 7 at stride 4)."""
    return max(3, 2 * stride - 1)


def repeat_pixels(x: torch.Tensor, factor: int) -> torch.Tensor:
    """Each pixel of B x C x S x h x w repeated ``factor`` x ``factor`` times (nearest
    upsampling). In an ONNX export as a broadcast and a reshape (the same values): ONNX
    Runtime's Resize takes 13.4 ms for a one-channel mask of four views at 480 px, the
    broadcast 2.3 ms."""
    if not torch.onnx.is_in_onnx_export():
        return F.interpolate(x, scale_factor=(1, factor, factor), mode="nearest")
    b, c, s, h, w = x.shape
    wide = x[:, :, :, :, None, :, None].expand(b, c, s, h, factor, w, factor)
    return wide.reshape(b, c, s, h * factor, w * factor)


class ResidualViewEncoder(nn.Module):
    """Per-view 2D features (shared weights), stacked into a volume, refined across views."""

    def __init__(self, cout: int, stride: int = 1, cin: int = 1, full: int | None = None):
        super().__init__()
        self.cin = cin
        # stride 2: a full-resolution layer first (``full`` channels, default cout / 2), whose
        # features the Main output gets back
        full = full or cout // 2
        self.full = conv_bn_act(cin, full, dims=2) if stride > 1 else None
        first = full if stride > 1 else cin
        self.per_view = nn.Sequential(
            conv_bn_act(first, cout, _stem_kernel(stride), stride=stride, dims=2),
            conv_bn_act(cout, cout, dims=2),
        )
        self.cross_view = nn.Sequential(
            conv_bn_act(cout, cout, kernel=(3, 1, 1)),
            conv_bn_act(cout, cout, kernel=(3, 1, 1), act=False),
        )

    @staticmethod
    def _volume(f: torch.Tensor, b: int) -> torch.Tensor:  # (B*S) x C x h x w -> B x C x S x h x w
        return f.reshape(b, -1, *f.shape[1:]).transpose(1, 2)

    def forward(self, x):
        """B x (S * cin) x H x W -> (volume B x C x S x h x w, the full-resolution volume
        B x full x S x H x W with stride 2, else None)."""
        b, sc, h, w = x.shape
        f = x.reshape(b * (sc // self.cin), self.cin, h, w)
        full = None
        if self.full is not None:
            f = self.full(f)
            full = self._volume(f, b)
        f = self._volume(self.per_view(f), b)
        return F.relu(f + self.cross_view(f), inplace=True), full


class PlainStem(nn.Module):
    """The stem without RVE: 3x3x3 convolutions over the views' channels; with stride 2 a
    full-resolution layer first, then a (1,2,2)-strided one (see the module docstring)."""

    def __init__(self, cout: int, stride: int = 1, cin: int = 1, full: int | None = None):
        super().__init__()
        full = full or cout // 2
        self.full = conv_bn_act(cin, full) if stride > 1 else None
        first = full if stride > 1 else cin
        k = _stem_kernel(stride)
        self.conv = conv_bn_act(first, cout, (3, k, k), stride=(1, stride, stride))

    def forward(self, vol):
        """B x cin x S x H x W -> (volume, full-resolution volume or None)."""
        full = self.full(vol) if self.full is not None else None
        return self.conv(vol if full is None else full), full


class ODMVNet(nn.Module):
    """See the module docstring. ``ablation`` names a Table I row (:data:`ABLATION_ROWS`);
    each switch left None follows that row: ``residual`` and ``attention_gates`` ("+RB&AG"),
    ``aspp``, ``rve``, ``ocd_oaf``, ``ssvr`` ("+Multi-task"). ``norm``: "batch" (the paper) or
    "group" (see :func:`odmv.models.blocks.set_norm`). ``view_padding``: "zeros" or "circular"
    (the view axis as a ring, :func:`odmv.models.blocks.set_view_padding`). ``memory_format``:
    "channels_last" (faster, the same values) or "contiguous"
    (:func:`odmv.models.blocks.set_memory_format`). ``full_width``: channels of the
    full-resolution stage with ``stem_stride`` 2 (default None: base_width // 2).
    ``gate_init``: None (PyTorch's initialisation) or "neutral", every gate starting uniform
    (:func:`odmv.models.blocks.set_gate_init`). ``fusion_bound``: None (the paper) or the
    bound on the attention's share of the fusion's blend logits
    (:class:`odmv.models.blocks.OcclusionAwareFusion`); ``fusion_kernel`` its spatial
    attention's extent. ``availability`` (beyond the paper;
    None: off): the input carries each view's availability after its channels
    (:mod:`odmv.data.views`); a missing view's input is zeroed and the fusion gives it no
    weight, so its images cannot move the depth. ``head`` (beyond the paper): "depth" (None,
    the paper) or "phase", every view's phase, fringe order (``orders`` classes) and confidence
    besides the regressed depth (:mod:`odmv.models.phase`). ``separable`` (beyond the paper;
    the light net, conf/model/odmvnet_lite.yaml): every full 3D convolution depthwise-separable
    (:func:`odmv.models.blocks.set_separable`)."""

    LOSS_TERMS = ("aux", "view", "occlusion")  # the full model; a Table I row may lack some

    def __init__(
        self,
        base_width: int = 46,
        blocks: int = 2,
        ablation: str = "multitask",
        residual: bool | None = None,
        attention_gates: bool | None = None,
        aspp: bool | None = None,
        rve: bool | None = None,
        ocd_oaf: bool | None = None,
        ssvr: bool | None = None,
        aspp_rates: tuple[int, ...] = (2, 4, 6),
        activation_checkpointing: bool = False,
        norm: str = "batch",
        view_channels: int = 1,
        stem_stride: int = 1,
        levels: int = LEVELS,
        view_padding: str = "zeros",
        memory_format: str = "channels_last",
        full_width: int | None = None,
        gate_init: str | None = None,
        fusion_bound: float | None = None,
        fusion_kernel: tuple[int, int, int] = (3, 7, 7),
        availability: bool | None = None,
        head: str | None = None,
        orders: int | None = None,
        separable: bool = False,
    ):
        super().__init__()
        head, orders = check_head(head, orders)
        self.availability = bool(availability)
        if ablation not in ABLATION_ROWS:
            raise ValueError(f"ablation {ablation!r} unknown; choose from {list(ABLATION_ROWS)}")
        given = dict(
            residual=residual,
            attention_gates=attention_gates,
            aspp=aspp,
            rve=rve,
            ocd_oaf=ocd_oaf,
            ssvr=ssvr,
        )
        self.flags = {
            k: ABLATION_ROWS[ablation][k] if v is None else bool(v) for k, v in given.items()
        }
        residual, attention_gates, aspp, rve, ocd_oaf, ssvr = (self.flags[k] for k in SWITCHES)
        if stem_stride not in STEM_STRIDES:
            raise ValueError(f"stem_stride {stem_stride} unsupported; choose 1, 2 or 4")
        if levels < 3:
            raise ValueError(f"levels {levels}: at least 3 encoder stages (Main, Aux1, Aux2)")
        if full_width is not None and (stem_stride == 1 or full_width < 1):
            raise ValueError(
                f"full_width {full_width}: a positive channel count, and only with stem_stride > 1"
            )
        self.stride, self.levels = stem_stride, levels
        w = [base_width * 2**i for i in range(levels + 1)]
        fw = full_width or w[0] // 2  # the full-resolution stage at stride 2
        self.widths = w
        self.checkpointing = activation_checkpointing
        self.view_channels = view_channels
        self.stem = (
            ResidualViewEncoder(w[0], stem_stride, view_channels, fw)
            if rve
            else PlainStem(w[0], stem_stride, view_channels, fw)
        )
        self.encoder = nn.ModuleList(
            stage3d(w[max(i - 1, 0)], w[i], blocks, residual) for i in range(levels)
        )
        self.pool = nn.MaxPool3d((1, 2, 2))
        last, neck = w[levels - 1], w[levels]
        if aspp:
            first = ResBlock3d(last, neck) if residual else conv_bn_act(last, neck)
            self.bottleneck = nn.Sequential(first, ASPP3d(neck, neck, aspp_rates))
        else:
            self.bottleneck = stage3d(last, neck, blocks, residual)
        self.up = nn.ModuleList(
            nn.ConvTranspose3d(w[i + 1], w[i], (1, 2, 2), stride=(1, 2, 2)) for i in range(levels)
        )
        stages = range(levels)
        self.decoder = nn.ModuleList(stage3d(2 * w[i], w[i], blocks, residual) for i in stages)
        self.gates = (
            nn.ModuleList(AttentionGate3d(w[i], w[i + 1], max(4, w[i] // 2)) for i in stages)
            if attention_gates
            else None
        )
        self.ocd = nn.ModuleList(OcclusionDetector(w[i]) for i in stages) if ocd_oaf else None
        # stride 2: the full-resolution stage after the decoder (see the module docstring)
        if stem_stride > 1:
            up = (1, stem_stride, stem_stride)
            self.up_full = nn.ConvTranspose3d(w[0], fw, up, stride=up)
            self.decoder_full = conv_bn_act(2 * fw, fw)
        # output heads Main, Aux1, Aux2: the channels of the stages they read
        head_ch = [w[0], w[1], w[2]] if stem_stride == 1 else [fw, w[0], w[1]]
        self.fusion = (
            nn.ModuleList(
                OcclusionAwareFusion(c, bound=fusion_bound, kernel=fusion_kernel) for c in head_ch
            )
            if ocd_oaf
            else None
        )
        self.heads = nn.ModuleList(RegressionHead(c) for c in head_ch)
        # head=phase: every view's phase, order and confidence from Main's per-view features
        self.phase_head = PhaseHead3d(head_ch[0], head_ch[0], orders) if head == "phase" else None
        self.ssvr = (
            nn.Sequential(
                conv_bn_act(head_ch[0], head_ch[0] // 2), nn.Conv3d(head_ch[0] // 2, 1, 1)
            )
            if ssvr
            else None
        )
        set_separable(self, separable)
        set_norm(self, norm)
        set_gate_init(self, gate_init)
        set_view_padding(self, view_padding)
        set_memory_format(self, memory_format, stems=(self.stem,))

    def _run(self, module, *args):
        if self.checkpointing and self.training and torch.is_grad_enabled():
            return checkpoint(module, *args, use_reentrant=False)
        return module(*args)

    def forward(self, x: torch.Tensor) -> dict:
        """``x``: B x (S * view_channels) x H x W, each view's channels together."""
        if x.ndim != 4:
            raise ValueError(f"ODMVNet expects B x S x H x W fringes, got shape {tuple(x.shape)}")
        b, sc, h, wd = x.shape
        m = self.stride * 2**self.levels
        if h % m or wd % m:
            raise ValueError(f"ODMVNet needs H and W divisible by {m}, got {h}x{wd}")
        per_view = self.view_channels + self.availability
        if sc % per_view:
            raise ValueError(f"ODMVNet expects {per_view} channels per view, got {sc}")
        available = None
        if self.availability:
            x, available = split_availability(x, sc // per_view)
            x = x * available.repeat_interleave(self.view_channels, 1)[..., None, None]
            sc = x.shape[1]
        if self.flags["rve"]:
            f, full = self.stem(x)
        else:  # B x C x S x H x W volume of the views' channels
            vol = x.reshape(b, sc // self.view_channels, self.view_channels, h, wd)
            f, full = self.stem(vol.transpose(1, 2))
        skips = []
        for i, stage in enumerate(self.encoder):
            f = self._run(stage, f if i == 0 else self.pool(f))
            skips.append(f)
        f = self._run(self.bottleneck, self.pool(f))
        masks: list[torch.Tensor | None] = [None] * self.levels
        stages, stage_masks = {}, {}  # decoder output and OCD mask per level
        for i in reversed(range(self.levels)):
            skip = skips[i]
            if self.ocd is not None:
                masks[i] = self.ocd[i](skip)
                skip = skip * masks[i]
            if self.gates is not None:
                skip = self.gates[i](skip, f)
            f = self._run(self.decoder[i], torch.cat([self.up[i](f), skip], 1))
            stages[i], stage_masks[i] = f, masks[i]
        # the stages that Main, Aux1 and Aux2 read
        if full is None:
            heads_in = [(stages[i], stage_masks[i]) for i in range(3)]
        else:
            f = self._run(self.decoder_full, torch.cat([self.up_full(f), full], 1))
            mask = masks[0]
            if mask is not None:  # the level-0 mask, repeated to full resolution
                mask = repeat_pixels(mask, self.stride)
            heads_in = [(f, mask), (stages[0], masks[0]), (stages[1], masks[1])]
        fused, blend = [], None  # blend: Main's fusion weights over the views
        for k, (feat, mask) in enumerate(heads_in):
            if self.fusion is not None:
                features, weights = self.fusion[k](feat, mask, available)
                fused.append(features)
                blend = weights if k == 0 else blend
            else:
                fused.append(view_mean(feat, available))
        outs = [head(f) for head, f in zip(self.heads, fused, strict=True)]
        result = {"depth": outs[0], "aux": outs[1:]}
        if self.phase_head is not None:
            # Main's fusion weights over the views become part of their confidences (as logits)
            logits = None if blend is None else torch.log(blend.clamp_min(1e-6))
            result |= self.phase_head(heads_in[0][0], fused[0], logits)
        if self.ssvr is not None:
            result["views"] = torch.tanh(self.ssvr(heads_in[0][0])[:, 0])
        if self.ocd is not None:
            result["occlusion"] = masks
        return result


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters())


def parameter_breakdown(net: ODMVNet) -> dict[str, int]:
    """Parameters per top-level module, in construction order."""
    return {name: count_parameters(m) for name, m in net.named_children()}
