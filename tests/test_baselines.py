import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import get_class, instantiate

from odmv.config import CONF_DIR, baselines, compose_train, model_configs, nets
from odmv.models import HNet, MTLNet, UNet, count_parameters
from odmv.training.losses import OPTIONAL_TERMS, LossWeights, composite_loss
from odmv.training.run import train

# the baselines of the registry (conf/model/): each a class taking in_channels and base_width
NETS = [get_class(model_configs()[name].model.net._target_) for name in baselines()]


@pytest.mark.parametrize(
    "name", [n for n in nets() if "published_parameters" in model_configs()[n].model]
)
def test_published_widths_give_published_parameter_counts(name):
    cfg = compose_train([f"model={name}"])  # the paper's protocol: every net at its published width
    with torch.device("meta"):
        n = count_parameters(instantiate(cfg.model.net))
    assert abs(n / cfg.model.published_parameters - 1) < 0.03, n


@pytest.mark.parametrize("cls", NETS)
@pytest.mark.parametrize("views", [1, 3])
def test_shapes_and_every_parameter_gets_a_gradient(cls, views):
    torch.manual_seed(0)
    net = cls(in_channels=views, base_width=8).train()  # >= 2 channels per UHRNet branch
    x = torch.rand(2, views, 32, 48) * 2 - 1
    out = net(x)
    assert out["depth"].shape == (2, 1, 32, 48)
    assert {t for t, key in OPTIONAL_TERMS.items() if key in out} == set(cls.LOSS_TERMS)
    batch = {
        "depth": torch.rand(2, 1, 32, 48),
        "fringes": x,
        "lit": torch.ones(2, views, 32, 48),
        "phase_target": torch.rand(2, 2 * views, 32, 48) * 2 - 1,
    }
    if cls is HNet:
        assert [a.shape for a in out["aux"]] == [(2, 1, 32, 48)] * 5
    if cls is MTLNet:
        assert out["phase"].shape == (2, 2 * views, 32, 48) and out["phase"].abs().max() <= 1
    weights = LossWeights(aux=[1.0] * 5)
    composite_loss(out, batch, weights)["loss"].backward()
    missing = [n for n, p in net.named_parameters() if p.grad is None or not p.grad.abs().sum() > 0]
    assert not missing, missing


def test_inputs_must_fit_the_pooling():
    with pytest.raises(ValueError, match="divisible by 16"):
        UNet(base_width=4)(torch.zeros(1, 1, 40, 32))


@pytest.mark.parametrize("model", baselines())
def test_two_training_steps_through_train(model, tiny_dataset, tmp_path):
    overrides = [
        f"model={model}",
        "data=exr",
        f"root={tiny_dataset}",
        "data.resolution=32",
        "data.batch_size=2",
        "data.num_workers=0",
        "data.progress=false",
        f"data.cache_dir={tmp_path}/cache",
        "model.net.base_width=4",
        "trainer.max_epochs=1",
        "trainer.accelerator=cpu",
        "trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false",
        "trainer.limit_train_batches=2",
        f"paths.output_dir={tmp_path}",
        "log_images=1",
    ]
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    assert list(cfg.data.views) == ["right"] and cfg.model.net.in_channels == 1
    metrics = train(cfg)
    ckpt = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=True)
    assert ckpt["global_step"] == 2
    assert metrics["test/mae_mm"] > 0
    if model == "mtlnet":
        assert cfg.data.with_phase
