"""Building blocks shared by the networks: 2D/3D conv blocks, residual blocks, attention gates,
3D ASPP, the occlusion detector and occlusion-aware fusion.

3D tensors are B x C x S x H x W: the view axis S is the depth axis of every 3D convolution, and
spatial downsampling never touches it.
"""

from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F


def reachable_taps(
    weight: torch.Tensor, size: tuple[int, ...], padding, dilation, stride
) -> tuple[torch.Tensor, tuple[int, ...]]:
    """The kernel taps of a zero-padded, same-size convolution that can meet the input, and
    the padding that keeps the output size: along a stride-1 axis of ``size`` points, a tap
    ``j`` steps from the centre at dilation ``d`` lies in the padding for every output point
    once ``j * d >= size``. Dropping such taps changes no value and saves their work: the
    ASPP branches at a 2 x 2 bottleneck (dilations 2-6) and every view kernel of a one-view
    volume reduce to their centre."""
    pads = []
    for axis, (n, p, d, s) in enumerate(zip(size, padding, dilation, stride, strict=True)):
        k = weight.shape[2 + axis]
        reach = min(k // 2, (n - 1) // d)
        if s == 1 and k % 2 and p == d * (k // 2) and reach < k // 2:
            weight = weight.narrow(2 + axis, k // 2 - reach, 2 * reach + 1)
            p = d * reach
        pads.append(p)
    return weight, tuple(pads)


class _ReachableTaps:
    """A zero-padded convolution that skips the taps which only ever meet padding at the
    input's size (:func:`reachable_taps`): the same values, the same parameters, less work."""

    def _conv_forward(self, x, weight, bias, padding=None):
        padding = self.padding if padding is None else padding
        weight, padding = reachable_taps(weight, x.shape[2:], padding, self.dilation, self.stride)
        return self._conv(x, weight, bias, self.stride, padding, self.dilation, self.groups)


class Conv2d(_ReachableTaps, nn.Conv2d):
    _conv = staticmethod(F.conv2d)


class Conv3d(_ReachableTaps, nn.Conv3d):
    """In an ONNX export, a depthwise convolution or one on at most two channels (the fusion's
    spatial attention) runs as a 2D one with the views folded into the channels
    (:func:`views_as_channels`): the same values, faster in ONNX Runtime."""

    _conv = staticmethod(F.conv3d)

    def folds_views(self) -> bool:
        unit_stride = all(s == 1 for s in self.stride)
        return unit_stride and self.in_channels // self.groups <= 2 and self.padding_mode == "zeros"

    def forward(self, x):
        if torch.onnx.is_in_onnx_export() and self.folds_views():
            return views_as_channels(self, x)
        return super().forward(x)


def conv_bn_act(
    cin: int, cout: int, kernel=3, stride=1, dilation=1, dims: int = 3, act: bool = True
) -> nn.Sequential:
    """Convolution (same padding), batch norm and ReLU, in 2D or 3D."""
    Conv, Norm = (Conv3d, nn.BatchNorm3d) if dims == 3 else (nn.Conv2d, nn.BatchNorm2d)
    k = (kernel,) * dims if isinstance(kernel, int) else tuple(kernel)
    d = (dilation,) * dims if isinstance(dilation, int) else tuple(dilation)
    pad = tuple(dd * (kk // 2) for kk, dd in zip(k, d, strict=True))
    layers = [Conv(cin, cout, k, stride=stride, padding=pad, dilation=d, bias=False), Norm(cout)]
    if act:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


NORMS = ("batch", "group")


def _groups(channels: int, most: int = 8) -> int:
    return max(g for g in range(1, most + 1) if channels % g == 0)


class GroupNorm(nn.GroupNorm):
    """GroupNorm computed in float32 under autocast. On a CPU its bfloat16 backward over a
    channels-last volume runs 3.5x slower than the float32 one, which cost bf16-mixed
    training all the convolutions gained (docs/performance.md); in float32 it is the plain
    layer, the same values."""

    def forward(self, x):
        if x.dtype == torch.float32:
            return super().forward(x)
        with torch.autocast(x.device.type, enabled=False):
            return super().forward(x.float())


def set_norm(net: nn.Module, norm: str) -> nn.Module:
    """``norm="group"`` replaces every BatchNorm in ``net`` by a GroupNorm (up to 8 groups) with
    the same affine parameters: per-sample statistics, so training and evaluation normalize
    alike even at batch 2-4, where BatchNorm's running statistics lag behind fast-changing
    weights. ``"batch"`` keeps BatchNorm (the paper's choice)."""
    if norm not in NORMS:
        raise ValueError(f"norm {norm!r} unknown; choose from {list(NORMS)}")
    if norm == "batch":
        return net
    for name, child in net.named_children():
        if isinstance(child, nn.modules.batchnorm._BatchNorm):
            setattr(net, name, GroupNorm(_groups(child.num_features), child.num_features))
        else:
            set_norm(child, norm)
    return net


VIEW_PADDINGS = ("zeros", "circular")


class ViewCircularConv3d(Conv3d):
    """A Conv3d whose view axis (the first of D x H x W) wraps around: the four views right,
    down, left, up form a ring in which each view's neighbours are the two beside it, which
    zero padding would cut between up and right. Space keeps zero padding."""

    def forward(self, x):
        if torch.onnx.is_in_onnx_export() and self.folds_views():
            return views_as_channels(self, x)
        p = self.padding[0]
        x = F.pad(x, (0, 0, 0, 0, p, p), mode="circular")
        return self._conv_forward(x, self.weight, self.bias, (0, *self.padding[1:]))


def inner_softmax(x: torch.Tensor, dim: int) -> torch.Tensor:
    """``torch.softmax`` over an inner axis ``dim`` (views, orders). In an ONNX export it is
    written out as exp / sum (the same values): ONNX Runtime's Softmax on an inner axis
    transposes around it, 7x slower at 480 px (21.9 against 3.0 ms over four views, 2
    threads)."""
    if not torch.onnx.is_in_onnx_export():
        return torch.softmax(x, dim)
    e = torch.exp(x - x.amax(dim, keepdim=True))
    return e / e.sum(dim, keepdim=True)


def views_as_channels(conv: nn.Conv3d, x: torch.Tensor) -> torch.Tensor:
    """``conv(x)`` for a stride-1 3D convolution on B x C x S x H x W, computed as one 2D
    convolution with the views folded into the channels: each output view's kernel reads the
    input views its 3D kernel reaches (zero or circular view padding); a depthwise kernel one
    view deep stays depthwise. The same values. ONNX Runtime runs 2D convolutions in its
    blocked layout and 3D ones without it; at 480 px, four views, 2 threads: the fusion's
    spatial attention (2 -> 1 channels, 3 x 7 x 7) 34.8 instead of 52.2 ms, a depthwise
    3 x 3 x 3 one on 8 channels 27.8 instead of 37.6 ms. Used in ONNX exports."""
    b, c, s, h, w = x.shape
    taps = conv.kernel_size[0]
    depthwise = conv.groups == c == conv.out_channels
    if taps == 1 and depthwise:  # no view mixing: a depthwise 2D convolution on C x S channels
        weight, groups = conv.weight[:, :, 0].repeat_interleave(s, 0), c * s
    else:
        src = torch.arange(s)[:, None] + torch.arange(taps)[None] * conv.dilation[0]
        src = src - conv.padding[0]
        reach = torch.ones_like(src, dtype=torch.bool)
        if isinstance(conv, ViewCircularConv3d):
            src = src % s
        else:
            reach = (src >= 0) & (src < s)
        # which input view each output view's tap reads: S_out x taps x S_in
        reads = F.one_hot(src.clamp(0, s - 1), s).to(conv.weight.dtype) * reach[..., None]
        weight = torch.einsum("ocjyx,sjt->osctyx", conv.weight, reads)
        weight = weight.reshape(conv.out_channels * s, -1, *conv.kernel_size[1:])
        groups = conv.groups
    bias = None if conv.bias is None else conv.bias.repeat_interleave(s)
    x = x.reshape(b, c * s, h, w)
    y = F.conv2d(x, weight, bias, 1, conv.padding[1:], conv.dilation[1:], groups)
    return y.reshape(b, conv.out_channels, s, h, w)


def set_view_padding(net: nn.Module, mode: str) -> nn.Module:
    """``"circular"``: every 3D convolution that pads the view axis wraps it instead
    (:class:`ViewCircularConv3d`, same parameters); ``"zeros"`` keeps zero padding (the
    paper's nets, as far as it says)."""
    if mode not in VIEW_PADDINGS:
        raise ValueError(f"view_padding {mode!r} unknown; choose from {list(VIEW_PADDINGS)}")
    if mode == "zeros":
        return net
    for name, child in net.named_children():
        if type(child) in (nn.Conv3d, Conv3d) and child.padding[0] > 0:
            conv = ViewCircularConv3d(
                child.in_channels,
                child.out_channels,
                child.kernel_size,
                child.stride,
                child.padding,
                child.dilation,
                child.groups,
                child.bias is not None,
            )
            conv.load_state_dict(child.state_dict())
            setattr(net, name, conv)
        else:
            set_view_padding(child, mode)
    return net


class SeparableConv3d(nn.Sequential):
    """A 3D convolution factored into a depthwise one (each channel alone, the full kernel)
    and a pointwise 1x1x1 one (mixing channels): about k^3 + C_out instead of k^3 x C_out
    multiplications per input channel and voxel. The depthwise part runs on the narrower
    side: on the input where the channels grow or stay, after the pointwise one where they
    shrink (the decoder's concatenations), which ONNX Runtime runs 1.8x faster at 480 px."""

    def __init__(self, conv: nn.Conv3d):
        cin, cout = conv.in_channels, conv.out_channels
        k, s, p, d = conv.kernel_size, conv.stride, conv.padding, conv.dilation
        mid = min(cin, cout)
        depthwise = Conv3d(mid, mid, k, stride=s, padding=p, dilation=d, groups=mid, bias=False)
        pointwise = nn.Conv3d(cin, cout, 1, bias=conv.bias is not None)
        super().__init__(*((pointwise, depthwise) if cout < cin else (depthwise, pointwise)))


def set_separable(net: nn.Module, separable: bool) -> nn.Module:
    """``separable`` (beyond the paper; the light net's): every full 3D convolution in ``net``
    with a kernel wider than one voxel and at least 4 input channels becomes a
    :class:`SeparableConv3d` (freshly initialised). Stems on one or two channels, the
    fusion's 2-channel spatial attention and depthwise layers stay as they are."""
    if not separable:
        return net
    for name, child in net.named_children():
        full = isinstance(child, nn.Conv3d) and child.groups == 1 and child.in_channels >= 4
        if full and math.prod(child.kernel_size) > 1:
            setattr(net, name, SeparableConv3d(child))
        else:
            set_separable(child, separable)
    return net


def _last_conv(m: nn.Module) -> nn.Module | None:
    """The convolution whose output ``m`` gives (``m`` itself, or a Sequential's last), if any."""
    if isinstance(m, (nn.Conv2d, nn.Conv3d)):
        return m
    return _last_conv(m[-1]) if isinstance(m, nn.Sequential) and len(m) else None


@torch.no_grad()
def fold_batchnorm(net: nn.Module) -> nn.Module:
    """Every BatchNorm that follows a convolution in a Sequential folded into it (the weight
    scaled per output channel by its running statistics, the bias shifted) and replaced by an
    identity: the evaluated net's values, one layer fewer. For exports: ONNX Runtime fuses a
    BatchNorm into the convolution before it itself, but not across the reshapes of a folded
    depthwise one (:func:`views_as_channels`), where it cost 4.4 ms at 480 px."""
    for seq in [m for m in net.modules() if isinstance(m, nn.Sequential)]:
        for i in range(1, len(seq)):
            bn, conv = seq[i], _last_conv(seq[i - 1])
            if not isinstance(bn, nn.modules.batchnorm._BatchNorm) or conv is None:
                continue
            if bn.running_var is None:  # batch statistics even in eval: nothing to fold
                continue
            scale = torch.rsqrt(bn.running_var + bn.eps)
            shift = -bn.running_mean * scale
            if bn.affine:
                scale, shift = scale * bn.weight, shift * bn.weight + bn.bias
            bias = scale * conv.bias if conv.bias is not None else 0
            conv.weight = nn.Parameter(conv.weight * scale.view(-1, *[1] * (conv.weight.dim() - 1)))
            conv.bias = nn.Parameter(bias + shift)
            seq[i] = nn.Identity()
    return net


MEMORY_FORMATS = ("contiguous", "channels_last")


def set_memory_format(net: nn.Module, fmt: str, stems: tuple[nn.Module, ...] = ()) -> nn.Module:
    """``"channels_last"`` stores every 3D convolution's weight channels-last (channels
    innermost); the convolution backend then runs those convolutions, and the activations they
    pass on, in that layout. The values are the same; on a 2-core CPU (oneDNN) the ODMV-Net
    training step is 20-26 % faster, most of it in the backward of the wide, few-channel layers
    (docs/performance.md); on a GPU it is unmeasured. The 2D convolutions inside ``stems`` (the
    per-view layers whose B*S outputs are stacked into a volume) go channels-last too: stacked,
    their outputs are then a channels-last volume without a copy, where a contiguous one makes
    every 3D layer it reaches convert it first. Other 2D layers keep their layout: no clear gain
    was measured for them."""
    if fmt not in MEMORY_FORMATS:
        raise ValueError(f"memory_format {fmt!r} unknown; choose from {list(MEMORY_FORMATS)}")
    if fmt == "channels_last":
        for m in net.modules():
            if isinstance(m, nn.Conv3d | nn.ConvTranspose3d):
                m.weight.data = m.weight.data.contiguous(memory_format=torch.channels_last_3d)
        for m in (m for stem in stems for m in stem.modules()):
            if isinstance(m, nn.Conv2d):
                m.weight.data = m.weight.data.contiguous(memory_format=torch.channels_last)
    return net


class Float32Conv2d(nn.Conv2d):
    """A regression output layer that stays float32 under autocast: in bf16 a normalized depth
    near 1 has steps of 2**-7, i.e. 0.08 mm at the default 10 mm half range."""

    def forward(self, x):
        with torch.autocast(x.device.type, enabled=False):
            return super().forward(x.float())


class Float32ConvTranspose2d(nn.ConvTranspose2d):
    """:class:`Float32Conv2d` for the learned upsampling of depth maps."""

    def forward(self, x, output_size=None):
        with torch.autocast(x.device.type, enabled=False):
            return super().forward(x.float(), output_size)


class PlainBlock3d(nn.Sequential):
    """Two 3x3x3 conv-BN-ReLU layers: the vanilla 3D U-Net block."""

    def __init__(self, cin: int, cout: int, n_layers: int = 2):
        super().__init__(*[conv_bn_act(cin if i == 0 else cout, cout) for i in range(n_layers)])


class ResBlock3d(nn.Module):
    """Pre-addition residual block: conv-BN-ReLU, conv-BN, plus identity (1x1x1 if widths
    differ), then ReLU."""

    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.body = nn.Sequential(conv_bn_act(cin, cout), conv_bn_act(cout, cout, act=False))
        self.skip = nn.Identity() if cin == cout else conv_bn_act(cin, cout, kernel=1, act=False)

    def forward(self, x):
        return F.relu(self.body(x) + self.skip(x), inplace=True)


def stage3d(cin: int, cout: int, n_blocks: int, residual: bool) -> nn.Sequential:
    """A stage of ``n_blocks`` residual blocks, or one plain double-conv block."""
    if not residual:
        return nn.Sequential(PlainBlock3d(cin, cout, n_layers=max(2, n_blocks)))
    return nn.Sequential(*[ResBlock3d(cin if i == 0 else cout, cout) for i in range(n_blocks)])


class AttentionGate3d(nn.Module):
    """Additive attention gate (Oktay et al.): a coarser gating signal g decides, per voxel,
    how much of the skip features x pass."""

    def __init__(self, x_ch: int, g_ch: int, inter_ch: int):
        super().__init__()
        self.wx = nn.Conv3d(x_ch, inter_ch, 1, bias=False)
        self.wg = nn.Conv3d(g_ch, inter_ch, 1, bias=True)
        self.psi = nn.Sequential(nn.Conv3d(inter_ch, 1, 1), nn.Sigmoid())

    def logit_layers(self) -> list[nn.Module]:
        return [self.psi[0]]

    def forward(self, x, g):
        g = F.interpolate(g, size=x.shape[2:], mode="trilinear", align_corners=False)
        return x * self.psi(F.relu(self.wx(x) + self.wg(g), inplace=True))


class ASPP3d(nn.Module):
    """3D atrous spatial pyramid pooling: a 1x1x1 branch, 3x3x3 branches dilated in space
    only (rates), image-level pooling, concatenated and projected. Keeps the resolution."""

    def __init__(self, cin: int, cout: int, rates=(2, 4, 6)):
        super().__init__()
        self.branches = nn.ModuleList([conv_bn_act(cin, cout, kernel=1)])
        self.branches.extend(conv_bn_act(cin, cout, dilation=(1, r, r)) for r in rates)
        self.pool = nn.Sequential(nn.AdaptiveAvgPool3d(1), nn.Conv3d(cin, cout, 1), nn.ReLU())
        self.project = conv_bn_act(cout * (len(rates) + 2), cout, kernel=1)

    def forward(self, x):
        feats = [b(x) for b in self.branches]
        feats.append(self.pool(x).expand(-1, -1, *x.shape[2:]))
        return self.project(torch.cat(feats, 1))


class OcclusionDetector(nn.Module):
    """Lightweight per-view occlusion mask from 3D features: depthwise-separable 3D convs
    (depthwise 3x3x3 + pointwise) ending in a sigmoid, B x C x S x h x w -> B x 1 x S x h x w."""

    def __init__(self, ch: int, hidden: int | None = None):
        super().__init__()
        hidden = hidden or max(8, ch // 4)
        self.net = nn.Sequential(
            Conv3d(ch, ch, 3, padding=1, groups=ch, bias=False),
            nn.Conv3d(ch, hidden, 1, bias=False),
            nn.BatchNorm3d(hidden),
            nn.ReLU(inplace=True),
            Conv3d(hidden, hidden, 3, padding=1, groups=hidden, bias=False),
            nn.Conv3d(hidden, 1, 1),
        )

    def logit_layers(self) -> list[nn.Module]:
        return [self.net[-1]]

    def forward(self, x):
        return torch.sigmoid(self.net(x))


class OcclusionAwareFusion(nn.Module):
    """3D features -> 2D map by attention-weighted aggregation over the view axis.

    Channel-view attention (a shared MLP on average- and max-pooled spatial statistics, one
    weight per channel and view) and spatial attention (a 3D conv on channel-pooled maps, one
    logit per view and pixel) re-weight the features. Views are then combined by a softmax
    over S of the spatial logits, i.e. a per-pixel convex blend. The occlusion mask, when
    given, suppresses what the OCD finds occluded twice: it scales the features before any
    attention (the spatial attention's kernel spans neighbouring views, so an unmasked
    occluded view would still steer its neighbours' weights) and adds its log to the logits
    (so the blend gives that view almost no weight).

    ``bound`` (beyond the paper; None: the paper's unbounded logits) limits what the attention
    adds to the blend's logits to ±bound (a scaled tanh), so the attention can change one
    view's weight against another's by at most exp(2 * bound) and the mask, not the attention,
    decides where they disagree: unbounded, learned logits can cancel the log-mask.
    ``kernel``: the spatial attention's (views, height, width) extent (CBAM's 7 x 7 in space;
    the light net's 3 x 3 x 3 runs 5x faster at 480 px in ONNX Runtime).
    """

    def __init__(self, ch: int, reduction: int = 8, bound: float | None = None, kernel=(3, 7, 7)):
        super().__init__()
        if bound is not None and not bound > 0:
            raise ValueError(f"fusion_bound {bound}: a positive logit bound, or null")
        self.bound = bound
        hidden = max(4, ch // reduction)
        self.mlp = nn.Sequential(
            nn.Linear(ch, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, ch)
        )
        k = tuple(kernel)
        self.spatial = Conv3d(2, 1, k, padding=tuple(n // 2 for n in k))

    def logit_layers(self) -> list[nn.Module]:
        return [self.mlp[-1], self.spatial]

    def forward(self, x, mask=None, available=None):
        """The fused features B x C x h x w and the blend's weights over views B x S x h x w."""
        x, weights = self.attend(x, mask, available)
        return (x * weights).sum(2), weights[:, 0]

    def attend(self, x, mask=None, available=None):
        """The attended features and the blend's weights over views, B x 1 x S x h x w;
        ``available`` (B x S bool, or None: all): a missing view gets weight exactly 0."""
        if mask is not None:
            x = x * mask
        # channel-view attention: B x C x S weights
        avg = x.mean((3, 4)).transpose(1, 2)  # B x S x C
        mx = x.amax((3, 4)).transpose(1, 2)
        cv = torch.sigmoid(self.mlp(avg) + self.mlp(mx)).transpose(1, 2)[..., None, None]
        x = x * cv
        # spatial attention over views: B x 1 x S x h x w logits
        pooled = torch.cat([x.mean(1, keepdim=True), x.amax(1, keepdim=True)], 1)
        logits = self.spatial(pooled)
        x = x * torch.sigmoid(logits)
        if self.bound is not None:
            logits = self.bound * torch.tanh(logits / self.bound)
        if mask is not None:
            logits = logits + torch.log(mask.clamp_min(1e-4))
        if available is not None:
            logits = logits.masked_fill(~available[:, None, :, None, None], float("-inf"))
        return x, inner_softmax(logits, dim=2)


def split_availability(x: torch.Tensor, n_views: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A net's input with each view's availability after its channels (odmv.data.views),
    B x S * (C + 1) x H x W -> the inputs (B x S * C x H x W) and the availability (B x S bool,
    from the flag channel's mean)."""
    v = x.unflatten(1, (n_views, x.shape[1] // n_views))
    return v[:, :, :-1].flatten(1, 2), v[:, :, -1].mean((-2, -1)) > 0.5


def view_mean(x: torch.Tensor, available: torch.Tensor | None = None) -> torch.Tensor:
    """The mean over the views (B x C x S x h x w -> B x C x h x w) of the available ones
    (B x S bool; None: all)."""
    if available is None:
        return x.mean(2)
    w = available.to(x)[:, None, :, None, None]
    return (x * w).sum(2) / w.sum(2)


GATE_INITS = (None, "neutral")
#: the modules whose outputs are learned gates (each names its logit layers)
GATES = (AttentionGate3d, OcclusionDetector, OcclusionAwareFusion)


def set_gate_init(net: nn.Module, mode: str | None) -> nn.Module:
    """``"neutral"`` (beyond the paper): every learned gate in ``net`` (attention gates, OCD
    masks, the fusion's channel-view and spatial attention) starts uniform, its logit layer
    zeroed: each gate passes 0.5 everywhere and the fusion starts as the mean over views. A
    module that a Table I row adds then starts as the row before it up to a constant gain, and
    departs from it only where the loss asks. None: PyTorch's initialisation (the paper is
    silent on it)."""
    if mode not in GATE_INITS:
        raise ValueError(f"gate_init {mode!r} unknown; choose null or neutral")
    if mode is None:
        return net
    for module in net.modules():
        if isinstance(module, GATES):
            for layer in module.logit_layers():
                nn.init.zeros_(layer.weight)
                nn.init.zeros_(layer.bias)
    return net


class RegressionHead(nn.Sequential):
    """2D head: conv-BN-ReLU then a linear 1x1 conv to one channel (kept in float32)."""

    def __init__(self, cin: int, hidden: int | None = None, cout: int = 1):
        hidden = hidden or max(8, cin // 2)
        super().__init__(conv_bn_act(cin, hidden, dims=2), Float32Conv2d(hidden, cout, 1))
