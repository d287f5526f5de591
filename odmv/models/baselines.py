"""Single-view fringe-to-depth baselines of the paper's Table II, as 2D networks.

Every baseline takes B x S x H x W fringes with the S views stacked as input channels (S = 1,
the 'right' view, reproduces the paper's single-view runs; S > 1 is early fusion) and returns the
output dict of docs/models.md. Published widths give the published parameter counts (tested).

- :class:`UNet` (Nguyen et al., Sensors 2020): two 3x3 conv + LeakyReLU per level, widths
  32-64-128-256-512, max-pooling, 3x3 stride-2 transposed convs, concatenated skips, dropout at
  the bottleneck, linear 1x1 head. 8.6 M parameters.
- :class:`HNet` (Nguyen et al., h-shaped global guidance): the UNet trunk plus a guidance branch
  tapping the bottleneck and every decoder level (1x1 conv to one channel, learned transposed-conv
  upsampling to full resolution): five side outputs, fused by a 1x1 conv into the prediction.
  All six are supervised (``aux`` holds the side outputs).
- :class:`UHRNet` (Wang et al., 2023): multi-level residual conv blocks (a 1x1 residual path
  plus four branches of growing depth with dilations 1, 2 and 5, LeakyReLU) in a
  64-128-256-512-1024 encoder-decoder, and high-resolution fusion blocks that merge resampled
  encoder features of all scales into the first three skips. 30.3 M parameters (convs that
  feed a batch norm carry no bias here: batch norm cancels it, so it could never learn).
- :class:`MTLNet`: the paper cites a multi-task single-view network without details we could
  verify; this is the common design of the field: a shared UNet encoder, a depth decoder and an
  auxiliary decoder predicting the wrapped phase of every input view as (sin, cos), trained
  jointly (``phase``: B x 2S x H x W, supervised on lit pixels).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

from odmv.models.blocks import Conv2d, Float32Conv2d, Float32ConvTranspose2d, set_norm
from odmv.models.phase import PhaseHead2d, check_head


def _check(x: torch.Tensor, levels: int, name: str) -> None:
    if x.ndim != 4:
        raise ValueError(f"{name} expects B x S x H x W fringes, got shape {tuple(x.shape)}")
    if x.shape[-2] % 2**levels or x.shape[-1] % 2**levels:
        raise ValueError(
            f"{name} needs H and W divisible by {2**levels}, got {tuple(x.shape[-2:])}"
        )


def double_conv(cin: int, cout: int) -> nn.Sequential:
    """Two 3x3 convolutions with LeakyReLU (Nguyen et al. use no normalization)."""
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1),
        nn.LeakyReLU(0.1, inplace=True),
        nn.Conv2d(cout, cout, 3, padding=1),
        nn.LeakyReLU(0.1, inplace=True),
    )


def up2x(cin: int, cout: int) -> nn.ConvTranspose2d:
    """Learned 2x upsampling: 3x3 transposed conv, stride 2."""
    return nn.ConvTranspose2d(cin, cout, 3, stride=2, padding=1, output_padding=1)


class _UEncoder(nn.Module):
    """Four double-conv levels with max-pooling, then a dropout bottleneck."""

    def __init__(self, cin: int, widths: list[int], dropout: float):
        super().__init__()
        self.levels = nn.ModuleList(
            double_conv(cin if i == 0 else widths[i - 1], widths[i]) for i in range(len(widths) - 1)
        )
        self.bottleneck = nn.Sequential(double_conv(widths[-2], widths[-1]), nn.Dropout2d(dropout))

    def forward(self, x):
        skips = []
        for level in self.levels:
            x = level(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        return self.bottleneck(x), skips


class _UDecoder(nn.Module):
    """Transposed-conv upsampling, concatenated skip, double conv; returns every level."""

    def __init__(self, widths: list[int]):
        super().__init__()
        n = len(widths) - 1
        self.ups = nn.ModuleList(up2x(widths[i + 1], widths[i]) for i in reversed(range(n)))
        self.convs = nn.ModuleList(
            double_conv(2 * widths[i], widths[i]) for i in reversed(range(n))
        )

    def forward(self, x, skips):
        outs = []
        for up, conv, skip in zip(self.ups, self.convs, reversed(skips), strict=True):
            x = conv(torch.cat([up(x), skip], 1))
            outs.append(x)
        return outs  # coarse to fine; the last is full resolution


def _widths(base: int) -> list[int]:
    return [base * 2**i for i in range(5)]


def _phase_head(ch: int, in_channels: int, n_views, head, orders) -> PhaseHead2d | None:
    """With ``head=phase``, every view's phase, order and confidence from the last
    full-resolution features (:mod:`odmv.models.phase`); None with the depth head. ``n_views``
    (None: ``in_channels``) differs from the input channels when the input carries more than
    the fringe per view (odmv.data.reference)."""
    head, orders = check_head(head, orders)
    return PhaseHead2d(ch, n_views or in_channels, orders) if head == "phase" else None


def _with_phase(out: dict, phase: PhaseHead2d | None, features: torch.Tensor) -> dict:
    return out if phase is None else out | phase(features)


class UNet(nn.Module):
    LOSS_TERMS = ()  # odmv.training.losses.OPTIONAL_TERMS its outputs have

    def __init__(
        self,
        in_channels: int = 1,
        base_width: int = 32,
        dropout: float = 0.5,
        n_views: int | None = None,
        head: str | None = None,
        orders: int | None = None,
    ):
        super().__init__()
        widths = _widths(base_width)
        self.encoder = _UEncoder(in_channels, widths, dropout)
        self.decoder = _UDecoder(widths)
        self.head = Float32Conv2d(widths[0], 1, 1)
        self.phase = _phase_head(widths[0], in_channels, n_views, head, orders)
        self.levels = len(widths) - 1

    def forward(self, x):
        _check(x, self.levels, "UNet")
        bottom, skips = self.encoder(x)
        f = self.decoder(bottom, skips)[-1]
        return _with_phase({"depth": self.head(f)}, self.phase, f)


class HNet(nn.Module):
    LOSS_TERMS = ("aux",)  # side outputs, deeply supervised

    def __init__(
        self,
        in_channels: int = 1,
        base_width: int = 32,
        dropout: float = 0.5,
        n_views: int | None = None,
        head: str | None = None,
        orders: int | None = None,
    ):
        super().__init__()
        widths = _widths(base_width)
        n = len(widths) - 1
        self.levels = n
        self.encoder = _UEncoder(in_channels, widths, dropout)
        self.decoder = _UDecoder(widths)
        # guidance taps: bottleneck (1/2^n) and decoder levels (1/2^(n-1) .. 1/1)
        tap_widths = [widths[n]] + [widths[i] for i in reversed(range(n))]
        self.taps = nn.ModuleList(Float32Conv2d(w, 1, 1) for w in tap_widths)
        self.ups = nn.ModuleList()
        for k in range(len(tap_widths)):
            factor = 2 ** (n - k) if k else 2**n
            self.ups.append(
                Float32ConvTranspose2d(1, 1, 2 * factor, stride=factor, padding=factor // 2)
                if factor > 1
                else nn.Identity()
            )
        self.fuse = Float32Conv2d(len(tap_widths), 1, 1)
        self.phase = _phase_head(widths[0], in_channels, n_views, head, orders)

    def forward(self, x):
        _check(x, self.levels, "HNet")
        bottom, skips = self.encoder(x)
        feats = [bottom] + self.decoder(bottom, skips)
        sides = [up(tap(f)) for f, tap, up in zip(feats, self.taps, self.ups, strict=True)]
        out = {"depth": self.fuse(torch.cat(sides, 1)), "aux": sides}
        return _with_phase(out, self.phase, feats[-1])


class _MultiLevelConv(nn.Module):
    """UHRNet's residual block: a 1x1 conv-BN path plus four branches (1 to 4 convs deep, the
    deepest dilated 2 and 5), each cout/4 wide, concatenated, added, LeakyReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        q = cout // 4

        def cbr(a, b, dilation=1, act=True):
            layers = [
                Conv2d(a, b, 3, padding=dilation, dilation=dilation, bias=False),
                nn.BatchNorm2d(b),
            ]
            return layers + ([nn.LeakyReLU(inplace=True)] if act else [])

        self.residual = nn.Sequential(nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout))
        self.branches = nn.ModuleList(
            [
                nn.Sequential(*cbr(cin, q, act=False)),
                nn.Sequential(*cbr(cin, q), *cbr(q, q, act=False)),
                nn.Sequential(*cbr(cin, q), *cbr(q, q), *cbr(q, q, 2, act=False)),
                nn.Sequential(*cbr(cin, q), *cbr(q, q), *cbr(q, q, 2), *cbr(q, q, 5, act=False)),
            ]
        )

    def forward(self, x):
        return F.leaky_relu(self.residual(x) + torch.cat([b(x) for b in self.branches], 1))


def _cbl(cin: int, cout: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.LeakyReLU(inplace=True),
    )


class _HighResFusion(nn.Module):
    """Resample the other encoder scales to level ``i``, fuse them, then fuse with the skip."""

    def __init__(self, widths: list[int], i: int, others: list[int], branch_width: int):
        super().__init__()
        self.i, self.others = i, others
        self.resample = nn.ModuleList()
        for j in others:
            if j < i:  # finer -> coarser: strided conv
                f = 2 ** (i - j)
                self.resample.append(nn.Conv2d(widths[j], branch_width, f, stride=f))
            else:  # coarser -> finer: transposed conv
                f = 2 ** (j - i)
                self.resample.append(
                    nn.ConvTranspose2d(
                        widths[j], branch_width, 3, stride=f, padding=1, output_padding=f - 1
                    )
                )
        self.mix = _cbl(branch_width * len(others), widths[i])
        self.merge = _cbl(2 * widths[i], widths[i])

    def forward(self, skips):
        fused = self.mix(
            torch.cat([r(skips[j]) for r, j in zip(self.resample, self.others, strict=True)], 1)
        )
        return self.merge(torch.cat([skips[self.i], fused], 1))


class UHRNet(nn.Module):
    LOSS_TERMS = ()

    def __init__(
        self,
        in_channels: int = 1,
        base_width: int = 64,
        dropout: float = 0.3,
        norm: str = "batch",
        n_views: int | None = None,
        head: str | None = None,
        orders: int | None = None,
    ):
        super().__init__()
        w = _widths(base_width)
        self.levels = 4
        self.down = nn.ModuleList(
            _MultiLevelConv(in_channels if i == 0 else w[i - 1], w[i]) for i in range(4)
        )
        self.drop = nn.Dropout(dropout)
        self.bottom = _MultiLevelConv(w[3], w[4])
        self.ups = nn.ModuleList(up2x(w[i + 1], w[i]) for i in reversed(range(4)))
        self.convs = nn.ModuleList(_MultiLevelConv(2 * w[i], w[i]) for i in reversed(range(4)))
        # fusion into skips 0..2 from the other encoder levels 0..3 (the published layout)
        self.fusion = nn.ModuleList(
            [
                _HighResFusion(w, 0, [3, 2, 1], w[0] // 2),
                _HighResFusion(w, 1, [0, 2, 3], w[1] // 2),
                _HighResFusion(w, 2, [0, 1, 3], w[2] // 2),
            ]
        )
        self.head = Float32Conv2d(w[0], 1, 1)
        self.phase = _phase_head(w[0], in_channels, n_views, head, orders)
        set_norm(self, norm)

    def forward(self, x):
        _check(x, self.levels, "UHRNet")
        skips = []
        for block in self.down:
            x = block(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.bottom(self.drop(x))
        fused = [f(skips) for f in self.fusion] + [skips[3]]
        for up, conv, skip in zip(self.ups, self.convs, reversed(fused), strict=True):
            x = conv(torch.cat([up(x), skip], 1))
        return _with_phase({"depth": self.head(x)}, self.phase, x)


class MTLNet(nn.Module):
    LOSS_TERMS = ("phase",)

    def __init__(
        self,
        in_channels: int = 1,
        base_width: int = 32,
        dropout: float = 0.5,
        n_views: int | None = None,
        head: str | None = None,
        orders: int | None = None,
    ):
        super().__init__()
        widths = _widths(base_width)
        self.levels = len(widths) - 1
        self.encoder = _UEncoder(in_channels, widths, dropout)
        self.depth_decoder = _UDecoder(widths)
        self.phase_decoder = _UDecoder(widths)
        self.depth_head = Float32Conv2d(widths[0], 1, 1)
        # (sin, cos) of each view's phase; with head=phase also its order and confidence, all
        # from the phase decoder
        self.phase_head = _phase_head(widths[0], in_channels, n_views, head, orders) or nn.Conv2d(
            widths[0], 2 * (n_views or in_channels), 1
        )

    def forward(self, x):
        _check(x, self.levels, "MTLNet")
        bottom, skips = self.encoder(x)
        depth = self.depth_head(self.depth_decoder(bottom, skips)[-1])
        phase = self.phase_head(self.phase_decoder(bottom, skips)[-1])
        if isinstance(self.phase_head, PhaseHead2d):
            return {"depth": depth} | phase
        return {"depth": depth, "phase": torch.tanh(phase)}
