import pytest
import torch

from odmv.models import ABLATION_ROWS, ODMVNet, count_parameters
from odmv.models.blocks import (
    GATES,
    ASPP3d,
    AttentionGate3d,
    OcclusionAwareFusion,
    OcclusionDetector,
    ResBlock3d,
)
from odmv.models.odmvnet import ResidualViewEncoder
from odmv.training.losses import OPTIONAL_TERMS


def _tiny(**kw):
    torch.manual_seed(0)
    return ODMVNet(base_width=4, blocks=1, **kw)


@pytest.mark.parametrize("views", [1, 2, 3, 4])
@pytest.mark.parametrize("hw", [(32, 32), (32, 48)])
def test_output_shapes_and_ranges(views, hw):
    h, w = hw
    net = _tiny().eval()
    x = torch.rand(2, views, h, w) * 2 - 1
    with torch.no_grad():
        out = net(x)
    assert out["depth"].shape == (2, 1, h, w)
    assert [a.shape for a in out["aux"]] == [(2, 1, h // 2, w // 2), (2, 1, h // 4, w // 4)]
    assert out["views"].shape == (2, views, h, w)
    assert out["views"].abs().max() < 1
    scales = [(h >> i, w >> i) for i in range(4)]
    assert [m.shape for m in out["occlusion"]] == [(2, 1, views, a, b) for a, b in scales]
    for m in out["occlusion"]:
        assert 0 < m.min() and m.max() < 1
    assert {t for t, key in OPTIONAL_TERMS.items() if key in out} == set(ODMVNet.LOSS_TERMS)


def test_every_parameter_gets_a_gradient():
    net = _tiny().train()
    out = net(torch.rand(2, 4, 32, 32) * 2 - 1)
    loss = out["depth"].mean() + sum(a.mean() for a in out["aux"]) + out["views"].pow(2).mean()
    loss = loss + sum(m.mean() for m in out["occlusion"])
    loss.backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing, missing


def _has(net, kind):
    return any(isinstance(m, kind) for m in net.modules())


def test_ablation_rows_add_modules_in_order():
    counts = []
    for row in ABLATION_ROWS:
        net = _tiny(ablation=row).train()
        out = net(torch.rand(1, 3, 32, 32) * 2 - 1)
        (out["depth"].mean() + sum(a.mean() for a in out["aux"])).backward()
        flags = ABLATION_ROWS[row]
        assert _has(net, ResBlock3d) == flags["residual"]
        assert _has(net, AttentionGate3d) == flags["attention_gates"]
        assert _has(net, ASPP3d) == flags["aspp"]
        assert _has(net, ResidualViewEncoder) == flags["rve"]
        assert _has(net, OcclusionDetector) == flags["ocd_oaf"]
        assert ("occlusion" in out) == flags["ocd_oaf"]
        assert ("views" in out) == flags["ssvr"]
        counts.append(count_parameters(net))
    assert counts == sorted(counts) and len(set(counts)) == len(counts), counts


def test_a_switch_overrides_the_row():
    full, no_aspp = _tiny(), _tiny(aspp=False)
    assert _has(full, ASPP3d) and not _has(no_aspp, ASPP3d)
    assert count_parameters(no_aspp) < count_parameters(full)
    with pytest.raises(ValueError, match="ablation 'nope' unknown"):
        _tiny(ablation="nope")


def test_bad_input_sizes_are_refused():
    with pytest.raises(ValueError, match="divisible by 16"):
        _tiny()(torch.zeros(1, 4, 40, 32))
    with pytest.raises(ValueError, match="B x S x H x W"):
        _tiny()(torch.zeros(1, 32, 32))


def test_activation_checkpointing_gives_the_same_gradients():
    torch.manual_seed(0)
    x = torch.rand(1, 2, 32, 32)
    grads = []
    for ckpt in (False, True):
        net = _tiny(activation_checkpointing=ckpt).train()
        net(x)["depth"].sum().backward()
        grads.append(torch.cat([p.grad.flatten() for p in net.parameters() if p.grad is not None]))
    torch.testing.assert_close(grads[0], grads[1])


def test_group_norm_switch_replaces_every_batch_norm():
    import torch.nn as nn

    from odmv.models import UHRNet
    from odmv.models.blocks import GroupNorm

    nets = (ODMVNet(base_width=4, blocks=1, norm="group"), UHRNet(1, 8, 0.0, norm="group"))
    for net in nets:
        kinds = {type(m) for m in net.modules()}
        assert GroupNorm in kinds
        assert not any(issubclass(k, nn.modules.batchnorm._BatchNorm) for k in kinds)
        net.train()  # BatchNorm would mix the batch here; GroupNorm's statistics are per sample
        x = torch.randn(2, 4 if isinstance(net, ODMVNet) else 1, 32, 32)
        with torch.no_grad():
            both = net(x)["depth"]
            one = net(x[:1])["depth"]
        torch.testing.assert_close(both[:1], one, atol=1e-5, rtol=1e-4)
    with pytest.raises(ValueError, match="norm 'layer' unknown"):
        ODMVNet(base_width=4, blocks=1, norm="layer")


@pytest.mark.parametrize("full_width", [None, 6])
@pytest.mark.parametrize("row", ["multitask", "aspp"])  # the RVE and the plain stem
def test_strided_stem_keeps_the_output_scales(row, full_width):
    net = _tiny(stem_stride=2, ablation=row, full_width=full_width).train()
    fw = full_width or 2  # base width 4: half of it by default
    assert net.decoder_full[0].out_channels == fw and net.up_full.out_channels == fw
    assert net.stem.full[0].out_channels == fw and net.heads[0][0][0].in_channels == fw
    x = torch.rand(2, 3, 64, 64) * 2 - 1
    out = net(x)
    assert out["depth"].shape == (2, 1, 64, 64)
    assert [a.shape for a in out["aux"]] == [(2, 1, 32, 32), (2, 1, 16, 16)]
    if "views" in out:
        assert out["views"].shape == (2, 3, 64, 64)
    if "occlusion" in out:  # the backbone (and its OCD masks) run at half resolution
        assert [m.shape[-1] for m in out["occlusion"]] == [32, 16, 8, 4]
    loss = out["depth"].mean() + sum(a.mean() for a in out["aux"])
    loss = loss + out.get("views", torch.zeros(1)).pow(2).mean()
    (loss + sum(m.mean() for m in out.get("occlusion", []))).backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing, missing
    with pytest.raises(ValueError, match="divisible by 32"):
        net(torch.rand(1, 3, 48, 48))


def test_full_width_needs_the_strided_stem():
    with pytest.raises(ValueError, match="only with stem_stride > 1"):
        _tiny(full_width=8)
    # unset, the strided net is the one trained before the setting existed (its checkpoints
    # load): the parameter count of that net
    assert count_parameters(_tiny(stem_stride=2)) == 717_952
    assert count_parameters(_tiny(stem_stride=2, full_width=4)) > 717_952


def test_fusion_gives_a_view_the_occlusion_detector_rejects_almost_no_weight():
    torch.manual_seed(0)
    fusion = OcclusionAwareFusion(8).eval()
    x = torch.rand(2, 8, 4, 16, 16)
    x[:, :, 2] = 50.0  # an outlier view: it would dominate a plain blend
    mask = torch.ones(2, 1, 4, 16, 16)
    mask[:, :, 2] = 1e-6  # the OCD finds view 2 unlit
    with torch.no_grad():
        fused = fusion(x, mask)[0]
        without = fusion(x.clone(), None)[0]
    # the rejected view's features do not reach the output ...
    x_other = x.clone()
    x_other[:, :, 2] = -50.0
    with torch.no_grad():
        assert torch.allclose(fusion(x_other, mask)[0], fused, atol=1e-2)
        # ... while without the mask they do
        assert not torch.allclose(fusion(x_other, None)[0], without, atol=1e-2)


def test_a_bounded_fusion_keeps_each_views_weight_within_its_bound_of_the_masks_ratio():
    torch.manual_seed(0)
    x = torch.randn(2, 8, 4, 16, 16)
    mask = torch.rand(2, 1, 4, 16, 16) * 0.9 + 0.05
    ratio = lambda w: (w[:, :, :, None] / w[:, :, None, :]).log()  # noqa: E731
    spread = {}
    for bound in (None, 0.5):
        fusion = OcclusionAwareFusion(8, bound=bound).eval()
        with torch.no_grad():
            fusion.spatial.weight.mul_(100)  # attention logits far beyond the bound
            weights = fusion.attend(x, mask)[1]
        torch.testing.assert_close(weights.sum(2), torch.ones(2, 1, 16, 16))
        # log(w_i / w_j) - log(m_i / m_j): what the attention adds between two views
        spread[bound] = (ratio(weights) - ratio(mask)).abs().max().item()
    assert spread[0.5] <= 1.0 + 1e-5  # exp(2 * bound) at most
    assert spread[None] > 10  # unbounded, the attention overrides the mask
    net = _tiny(fusion_bound=0.5)
    assert [f.bound for f in net.fusion] == [0.5] * 3
    with pytest.raises(ValueError, match="fusion_bound"):
        _tiny(fusion_bound=0.0)


def test_circular_view_padding_makes_the_net_equivariant_to_rotating_the_views():
    x = torch.rand(1, 4, 32, 32) * 2 - 1
    rolled = x.roll(1, dims=1)  # right, down, left, up -> up, right, down, left
    for padding, equivariant in (("circular", True), ("zeros", False)):
        net = _tiny(view_padding=padding, norm="group").eval()
        with torch.no_grad():
            a, b = net(x), net(rolled)
        same = torch.allclose(a["depth"], b["depth"], atol=1e-5)
        assert same == equivariant, padding
        if equivariant:
            torch.testing.assert_close(b["views"], a["views"].roll(1, dims=1), atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="view_padding"):
        _tiny(view_padding="reflect")


def test_channels_last_gives_the_same_outputs_and_gradients():
    # a fixed input: on some inputs float rounding flips a max-pool or amax choice, which moves
    # a few gradients as much as running the contiguous net on 1 thread instead of 2 does
    torch.manual_seed(0)
    x = torch.rand(2, 4, 32, 32) * 2 - 1
    results = []
    for fmt in ("contiguous", "channels_last"):
        net = _tiny(memory_format=fmt, norm="group", stem_stride=2).train()
        conv3d = [m.weight for m in net.modules() if isinstance(m, torch.nn.Conv3d)]
        assert all(
            w.is_contiguous(memory_format=torch.channels_last_3d) == (fmt == "channels_last")
            for w in conv3d
            if w.shape[1] > 1 and w.shape[-3:].numel() > 1  # else both layouts are one
        )
        out = net(x)
        (out["depth"].sum() + out["views"].square().sum()).backward()
        grads = torch.cat([p.grad.flatten() for p in net.parameters() if p.grad is not None])
        results.append((out["depth"].detach(), grads))
    torch.testing.assert_close(results[1][0], results[0][0], atol=1e-5, rtol=1e-4)
    # gradients span 1e-6 to several 1e3: float32 rounding is judged against the largest
    grads = results[0][1]
    torch.testing.assert_close(results[1][1], grads, atol=1e-5 * grads.abs().max(), rtol=1e-3)
    with pytest.raises(ValueError, match="memory_format"):
        _tiny(memory_format="blocked")


def test_neutral_gate_init_starts_every_gate_uniform_and_the_gates_still_learn():
    net = _tiny(gate_init="neutral", stem_stride=2, norm="group").train()
    seen = {"fusion": [], "gate": []}
    for m in net.modules():
        if isinstance(m, OcclusionAwareFusion):
            m.register_forward_hook(lambda _m, a, out: seen["fusion"].append((a[0], out)))
        if isinstance(m, AttentionGate3d):
            m.register_forward_hook(lambda _m, a, out: seen["gate"].append((a[0], out)))
    x = torch.rand(2, 4, 32, 32) * 2 - 1
    out = net(x)
    assert all(torch.equal(m, torch.full_like(m, 0.5)) for m in out["occlusion"])
    # features x mask 0.5 x channel-view 0.5 x spatial 0.5, blended with equal weights
    for feats, (fused, weights) in seen["fusion"]:
        torch.testing.assert_close(fused, 0.125 * feats.mean(2))
        torch.testing.assert_close(weights, torch.full_like(weights, 0.25))
    for feats, gated in seen["gate"]:
        torch.testing.assert_close(gated, 0.5 * feats)
    assert len(seen["fusion"]) == 3 and len(seen["gate"]) == 4
    # one step on the depth outputs moves every gate's logit layer off zero
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    sum((d - torch.rand_like(d)).abs().mean() for d in [out["depth"], *out["aux"]]).backward()
    opt.step()
    logits = [layer for m in net.modules() if isinstance(m, GATES) for layer in m.logit_layers()]
    assert len(logits) == 4 + 4 + 2 * 3
    still = [layer for layer in logits if not layer.weight.abs().sum() > 0]
    assert not still, still
    # PyTorch's initialisation (the default) gives masks that vary
    with torch.no_grad():
        masks = _tiny(stem_stride=2, norm="group")(x)["occlusion"]
    assert all(m.std() > 0 for m in masks)
    with pytest.raises(ValueError, match="gate_init"):
        _tiny(gate_init="zeros")


@pytest.mark.parametrize(
    "layer, size",
    [
        # an ASPP branch at a 2 x 2 bottleneck: only the centre of space meets the input
        (dict(cin=8, cout=6, kernel_size=3, padding=(1, 6, 6), dilation=(1, 6, 6)), (4, 2, 2)),
        # a one-view volume: the view kernel's outer taps meet only the zero padding
        (dict(cin=8, cout=6, kernel_size=3, padding=1), (1, 5, 5)),
        (dict(cin=2, cout=1, kernel_size=(3, 7, 7), padding=(1, 3, 3)), (1, 2, 3)),
        # UHRNet's dilation-5 branch at its 4 x 4 bottleneck (2D)
        (dict(cin=8, cout=6, kernel_size=3, padding=5, dilation=5), (4, 4)),
    ],
)
def test_skipping_taps_that_meet_only_padding_keeps_values_and_gradients(layer, size):
    from odmv.models.blocks import Conv2d, Conv3d, reachable_taps

    dims = len(size)
    ours = (Conv3d if dims == 3 else Conv2d)(layer.pop("cin"), layer.pop("cout"), **layer)
    plain = (torch.nn.Conv3d if dims == 3 else torch.nn.Conv2d)(
        ours.in_channels, ours.out_channels, **layer
    )
    plain.load_state_dict(ours.state_dict())
    trimmed, _ = reachable_taps(ours.weight, size, ours.padding, ours.dilation, ours.stride)
    assert trimmed.shape[2:].numel() < ours.weight.shape[2:].numel()  # work is skipped
    x = torch.rand(3, ours.in_channels, *size)
    results = []
    for conv in (plain, ours):
        out = conv(x)
        out.square().sum().backward()
        results.append((out.detach(), conv.weight.grad, conv.bias.grad))
    for a, b in zip(*results, strict=True):
        torch.testing.assert_close(b, a, atol=1e-5, rtol=1e-5)
    # a tap that never meets the input gets no gradient, as in the plain convolution
    assert results[1][1].shape == ours.weight.shape


def test_stride_2_view_encoder_gives_channels_last_volumes():
    # per-view 2D features in channels-last are a channels-last volume once stacked, so the
    # 3D layers they reach never convert them (docs/performance.md); three channels a view, as
    # with the reference phase (one channel leaves a layer's layout ambiguous)
    x = torch.rand(2, 4 * 3, 32, 32)
    for fmt in ("channels_last", "contiguous"):
        vol, full = _tiny(stem_stride=2, view_channels=3, memory_format=fmt).stem(x)
        for v in (vol, full):
            assert v.is_contiguous(memory_format=torch.channels_last_3d) == (fmt != "contiguous")


@pytest.mark.parametrize("views", [1, 3, 4])
@pytest.mark.parametrize("circular", [False, True])
@pytest.mark.parametrize(
    "layer",
    [
        dict(cin=2, cout=1, kernel=(3, 7, 7), padding=(1, 3, 3)),  # the fusion's attention
        dict(cin=2, cout=3, kernel=(3, 5, 5), padding=(1, 4, 4), dilation=(1, 2, 2)),
        dict(cin=6, cout=6, kernel=3, padding=1, groups=6),  # depthwise across the views
        dict(cin=6, cout=6, kernel=(1, 3, 3), padding=(0, 1, 1), groups=6),  # within each view
    ],
)
def test_views_folded_into_channels_give_the_3d_convolution(views, circular, layer):
    """The export form of a 3D convolution over the views (one 2D convolution, the views as
    channels) gives its values, with zero or circular view padding."""
    from odmv.models.blocks import Conv3d, ViewCircularConv3d, views_as_channels

    torch.manual_seed(0)
    kind = ViewCircularConv3d if circular else Conv3d
    layer = dict(layer)
    conv = kind(layer.pop("cin"), layer.pop("cout"), layer.pop("kernel"), **layer)
    assert conv.folds_views()
    x = torch.randn(2, conv.in_channels, views, 9, 11)
    torch.testing.assert_close(views_as_channels(conv, x), conv(x), atol=1e-5, rtol=1e-5)


def test_the_exported_softmax_is_the_softmax():
    from odmv.models.blocks import inner_softmax

    x = torch.randn(2, 5, 3, 4)
    x[0, 1] = float("-inf")  # a missing view
    torch.testing.assert_close(inner_softmax(x, 1), torch.softmax(x, 1))

    class Exported(torch.nn.Module):
        def forward(self, x):
            return inner_softmax(x, 1)

    ort = pytest.importorskip("onnxruntime")
    program = torch.onnx.export(Exported(), (x,), dynamo=True, verbose=False)
    ops = {node.op_type for node in program.model_proto.graph.node}
    assert "Softmax" not in ops and "Exp" in ops  # written out, not ORT's inner-axis Softmax
    session = ort.InferenceSession(program.model_proto.SerializeToString())
    torch.testing.assert_close(
        torch.from_numpy(session.run(None, {"x": x.numpy()})[0]), torch.softmax(x, 1)
    )


def test_the_exported_pixel_repeat_is_nearest_upsampling():
    from odmv.models.odmvnet import repeat_pixels

    class Exported(torch.nn.Module):
        def forward(self, x):
            return repeat_pixels(x, 4)

    ort = pytest.importorskip("onnxruntime")
    x = torch.rand(2, 1, 3, 5, 6)
    program = torch.onnx.export(Exported(), (x,), dynamo=True, verbose=False)
    assert "Resize" not in {node.op_type for node in program.model_proto.graph.node}
    session = ort.InferenceSession(program.model_proto.SerializeToString())
    got = torch.from_numpy(session.run(None, {"x": x.numpy()})[0])
    torch.testing.assert_close(got, repeat_pixels(x, 4), atol=0, rtol=0)
    assert got.shape == (2, 1, 3, 20, 24)


def test_folding_the_batchnorms_keeps_the_evaluated_nets_values():
    """The export's BatchNorm folding on the light net (separable 3D convolutions, their
    depthwise part last where channels shrink) with trained-looking running statistics: the
    same depth, and no BatchNorm left after a convolution."""
    from odmv.models.blocks import fold_batchnorm

    torch.manual_seed(0)
    net = ODMVNet(base_width=4, blocks=1, stem_stride=4, levels=3, full_width=4, separable=True)
    for m in net.modules():
        if isinstance(m, torch.nn.modules.batchnorm._BatchNorm):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.2, 0.2)
    net.eval()
    x = torch.randn(1, 4, 32, 32)
    before = net(x)["depth"]
    norms = sum(isinstance(m, torch.nn.BatchNorm3d) for m in net.modules())
    fold_batchnorm(net)
    left = sum(isinstance(m, torch.nn.BatchNorm3d) for m in net.modules())
    assert norms > 10 and left == 0
    torch.testing.assert_close(net(x)["depth"], before, atol=1e-5, rtol=1e-4)
