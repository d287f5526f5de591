"""Phase-shifting sequences as rigs save them: file names, shift conventions, the fringe
frequencies, and the check that they were read right.

Real sequences differ from the twin's in how files are numbered, in the direction of the phase
shift and in the phase of the first image. :class:`PspOptions` names all of it (``psp.*`` of
``odmv.predict`` and ``odmv.convert``, docs/dataset.md); the decoding is
odmv.classical.fringe's. Read with
the wrong conventions, consecutive frequencies give fringe orders that disagree on most pixels:
:func:`check_conventions` says so in one line, with the conventions under which they agree.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from odmv.classical.fringe import decode_phase
from odmv.io.images import find_view_image

#: The twin's sequences: 1, 8 and 64 periods across the projector's 1920 px (odmv.io.manifest).
TWIN_PERIODS = (1.0, 8.0, 64.0)
#: Below this share of the modulated pixels kept by the unwrapping, the conventions are wrong.
MIN_AGREEMENT = 0.5
MIN_PIXELS = 100
#: The first phases tried when the orders disagree. The shift direction is not among the
#: things tried: read the wrong way round, a sequence at integer period ratios decodes to the
#: mirrored coordinate (the axis length minus the true one) whose orders agree, so it cannot be
#: told from the images alone.
ORIGINS_TRIED = [k * np.pi / 2 for k in range(4)]


class SequenceError(ValueError):
    """Sequences that cannot be read or decoded as named: one line naming the folder."""


@dataclass(frozen=True)
class PspOptions:
    """How a folder's phase-shifting sequences are named and what they encode.

    ``periods``: fringe periods across the projector's phase axis for each frequency, coarsest
    first (the coarsest one period, absolute, unless ``unwrap="spatial"``; None: the twin's).
    ``steps``: images per frequency (None: counted from the files). Image n of a frequency is
    A + B cos(phi + shift_sign 2 pi n / N + phase_origin_rad). ``pattern``: a file's stem,
    formatted with ``view``, ``f`` (frequency), ``s`` (step) and ``n`` (running number over
    both, f * steps + s), each counted from ``first_index``; any image format odmv reads.
    ``min_modulation``: fringe amplitude B (full-scale units) below which a pixel is rejected.
    """

    periods: tuple[float, ...] | None = None
    steps: int | None = None
    shift_sign: int = 1
    phase_origin_rad: float = 0.0
    pattern: str = "{view}_f{f}_s{s:02d}"
    first_index: int = 0
    min_modulation: float = 0.02
    unwrap: str = "temporal"

    @classmethod
    def from_cfg(cls, cfg) -> PspOptions:
        """From a ``psp:`` config node (unknown keys refused, each value checked)."""
        given = dict(cfg or {})
        unknown = sorted(set(given) - {f.name for f in fields(cls)})
        if unknown:
            raise ValueError(f"psp.{unknown[0]}: unknown option")
        if given.get("periods") is not None:
            given["periods"] = tuple(float(p) for p in given["periods"])
        options = cls(**given)
        options.check()
        return options

    def check(self) -> None:
        if self.periods is not None:
            if not self.periods or min(self.periods) <= 0:
                raise ValueError(f"psp.periods: {list(self.periods)} must be positive numbers")
            if list(self.periods) != sorted(self.periods):
                raise ValueError(f"psp.periods: {list(self.periods)} must run coarsest first")
            if self.periods[0] != 1 and self.unwrap != "spatial":
                raise ValueError(
                    f"psp.periods: the coarsest frequency has {self.periods[0]:g} periods; "
                    "temporal unwrapping needs one period across the projector (or "
                    "psp.unwrap=spatial, which gives a relative phase)"
                )
        if self.steps is not None and self.steps < 3:
            raise ValueError(f"psp.steps: {self.steps}; phase shifting needs at least 3")
        if self.shift_sign not in (1, -1):
            raise ValueError(f"psp.shift_sign: {self.shift_sign}; use 1 or -1")
        if self.first_index not in (0, 1):
            raise ValueError(f"psp.first_index: {self.first_index}; use 0 or 1")
        if self.unwrap not in ("temporal", "spatial"):
            raise ValueError(f"psp.unwrap: {self.unwrap!r}; use temporal or spatial")
        if not self.min_modulation >= 0:
            raise ValueError(f"psp.min_modulation: {self.min_modulation} must be >= 0")
        try:
            self.stem("right", 0, 0, 1)
        except (KeyError, IndexError, ValueError) as e:
            raise ValueError(
                f"psp.pattern: {self.pattern!r} is not a format of view, f, s and n ({e})"
            ) from None

    @property
    def frequencies(self) -> tuple[float, ...]:
        return self.periods if self.periods is not None else TWIN_PERIODS

    @property
    def per_view(self) -> bool:
        """Whether file names name the projector (else the folder holds one projector's)."""
        return "{view" in self.pattern

    def stem(self, view: str, f: int, s: int, steps: int) -> str:
        i = self.first_index
        return self.pattern.format(view=view, f=f + i, s=s + i, n=f * steps + s + i)

    def conventions(self) -> dict:
        """The keyword arguments of odmv.classical.fringe.decode_phase these options set."""
        return dict(
            shift_sign=self.shift_sign, phase_origin_rad=self.phase_origin_rad, unwrap=self.unwrap
        )


def views_in(folder: Path, options: PspOptions, candidates: list[str]) -> list[str]:
    """The candidate views whose first image is in ``folder``."""
    return [v for v in candidates if find_view_image(folder, options.stem(v, 0, 0, 1))]


def count_steps(folder: Path, options: PspOptions, view: str) -> int:
    """Images per frequency: ``psp.steps``, else the run of the first frequency's files (a
    running number ``n`` cannot tell where a frequency ends, so it needs ``psp.steps``)."""
    if options.steps is not None:
        return options.steps
    if "{n" in options.pattern:
        raise SequenceError(f"{folder}: psp.pattern numbers images with n; give psp.steps")
    steps = 0
    while find_view_image(folder, options.stem(view, 0, steps, 1)):
        steps += 1
    if steps < 3:
        raise SequenceError(
            f"{folder}: {steps} image(s) named like {options.stem(view, 0, 0, 1)}; phase "
            "shifting needs at least 3 per frequency (check psp.pattern and psp.first_index)"
        )
    return steps


def stems(options: PspOptions, view: str, steps: int) -> list[str]:
    """The file stems of one projector's sequences, frequency by frequency, step by step."""
    return [
        options.stem(view, f, s, steps)
        for f in range(len(options.frequencies))
        for s in range(steps)
    ]


def read_stack(folder: Path, options: PspOptions, view: str, steps: int, read) -> np.ndarray:
    """One projector's sequences in ``folder`` (F, N, H, W), ``read(folder, stems)`` giving
    their images (S, H, W) in linear intensity; refused when they decode to wrong orders."""
    images = read(folder, stems(options, view, steps))
    stack = images.reshape(len(options.frequencies), steps, *images.shape[-2:])
    check_conventions(stack, options, f"{folder}: {view}")
    return stack


def check_conventions(stack: np.ndarray, options: PspOptions, where: str) -> None:
    """Refuse one projector's sequences (F, N, H, W) that the options decode to wrong fringe
    orders on most modulated pixels, naming the conventions under which they agree. Needs two
    frequencies or more and MIN_PIXELS modulated pixels (else nothing can be told). The two
    coarsest frequencies are checked: a wrong first phase shows in any pair, and the finest may
    alias in the camera, which is no fault of the conventions."""
    if len(stack) < 2 or options.unwrap != "temporal":
        return
    stack = stack[:2]
    periods = [1 / p for p in options.frequencies[:2]]
    share = _agreement(stack, periods, options.min_modulation, **options.conventions())
    if share is None or share >= MIN_AGREEMENT:
        return
    shares = {
        origin: _agreement(stack, periods, options.min_modulation, options.shift_sign, origin)
        or 0.0
        for origin in ORIGINS_TRIED
    }
    best = max(shares, key=shares.get)
    hint = (
        f"with psp.phase_origin_rad={best:.5f} they agree on {shares[best]:.1%}"
        if shares[best] >= MIN_AGREEMENT
        else "no first phase fixes it: check psp.periods, psp.steps and the images' order"
    )
    raise SequenceError(
        f"{where}: consecutive frequencies give the same fringe order on only {share:.1%} of "
        f"the modulated pixels (shift_sign={options.shift_sign}, phase_origin_rad="
        f"{options.phase_origin_rad:g}, periods {list(options.frequencies)}); {hint}"
    )


def _agreement(stack, periods, min_modulation, shift_sign, phase_origin_rad, unwrap="temporal"):
    _, _, ok, modulated = decode_phase(
        stack, periods, min_modulation, shift_sign, phase_origin_rad, unwrap
    )
    if modulated.sum() < MIN_PIXELS:
        return None
    return float(ok[modulated].mean())
