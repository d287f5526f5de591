"""The rig's quarter-turn symmetry as training augmentation (beyond the paper).

The four projectors are one unit turned about the camera axis by multiples of 90 degrees, and
the camera's field is square and centred on that axis. A scene turned by +90 degrees about the
axis therefore images, under projector ``NEXT[v]``, as the original scene under projector ``v``
with the image turned by +90 degrees (``torch.rot90`` on rows and columns: world +x, image
right, goes to world +y, image up). ``python -m odmv.study symmetry`` renders scenes and their
turned copies to measure how exact this is on a given rig (exact to float rounding without the
camera's tangential distortion; the twin's default lens breaks it by at most 0.018 mm of
depth and 0.10 of full-scale intensity, at edges, on 12 scenes of the mini dataset).

So a training sample turned by ``k`` quarter turns is another valid sample of the same rig, if
each view's arrays are taken from the view that the turn maps onto it. A one-view net (S = 1,
``right``) then sees the other projectors' images turned into its own: the samples still come
from the rig it is trained for.
"""

from __future__ import annotations

import torch

#: the projector a +90 degree turn of the scene maps each projector's role onto
NEXT = {"right": "up", "up": "left", "left": "down", "down": "right"}
PREV = {b: a for a, b in NEXT.items()}
AUGMENTS = (None, "rot90")
#: a sample's per-view arrays (each view's channels together along the first axis), the arrays
#: that belong to the scene as a whole, and the metric subsets that name one projector (its
#: role passes to another in a turn; training, the only use of turned samples, needs none)
_PER_VIEW = ("fringes", "lit", "inputs", "phase_target")
_IMAGES = ("depth", "depth_mm", "valid", "shadowed", "unlit")
_DROPPED = ("first_unlit", "first_shadowed")


def source_views(views: tuple[str, ...], k: int) -> list[str]:
    """For each of ``views`` in a sample turned by ``k`` quarter turns, the view of the
    unturned sample its arrays come from."""
    out = []
    for v in views:
        for _ in range(k % 4):
            v = PREV[v]
        out.append(v)
    return out


def turn_sample(sample: dict, have: tuple[str, ...], want: tuple[str, ...], k: int) -> dict:
    """``sample`` (holding the views ``have``) turned by ``k`` quarter turns, with the per-view
    arrays of the views ``want``."""
    idx = [have.index(v) for v in source_views(want, k)]
    out = {k: v for k, v in sample.items() if k not in _DROPPED}
    for name in _PER_VIEW:
        if name in sample:
            x = sample[name]
            per = x.shape[0] // len(have)  # channels of one view, each view's together
            x = x.reshape(len(have), per, *x.shape[1:])[idx].reshape(-1, *x.shape[1:])
            out[name] = torch.rot90(x, k, dims=(-2, -1))
    for name in _IMAGES:
        out[name] = torch.rot90(sample[name], k, dims=(-2, -1))
    if "available" in sample:  # each view's availability (odmv.data.views) goes with its arrays
        out["available"] = sample["available"][idx]
    return out


class QuarterTurns(torch.utils.data.Dataset):
    """Each item of ``base`` (square samples of all four views, which the data module checks)
    turned by a random number of quarter turns, with the per-view arrays of ``views``. The
    turn is drawn from torch's generator, so a seeded run draws the same turns."""

    def __init__(self, base, views: tuple[str, ...]):
        self.base, self.have, self.views = base, tuple(base.spec.views), tuple(views)

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, i: int) -> dict:
        k = int(torch.randint(4, ()))
        return turn_sample(self.base[i], self.have, self.views, k)
