"""Networks: plain nn.Modules mapping B x S x H x W normalized fringes to a dict of outputs
(``depth`` B x 1 x H x W plus optional ``aux``, ``views``, ``occlusion``, ``phase``)."""

from odmv.models.baselines import HNet, MTLNet, UHRNet, UNet
from odmv.models.odmvnet import ABLATION_ROWS, ODMVNet, count_parameters, parameter_breakdown

__all__ = [
    "ABLATION_ROWS",
    "HNet",
    "MTLNet",
    "ODMVNet",
    "UHRNet",
    "UNet",
    "count_parameters",
    "parameter_breakdown",
]
