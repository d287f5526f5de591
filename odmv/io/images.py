"""Camera images in the formats rigs save: EXR, PNG, TIFF, BMP (8 or 16 bit, or float TIFF)
and NPY, read as linear intensity, with the intensity scale and any resizing stated, never
silent.

The network was trained on linear intensity with the saturation level at 1, so an image is
divided by its full-scale value: 255 for 8-bit, 65535 for 16-bit, 1 for float data (the
default, from the file's type; a 12-bit camera stored in 16-bit PNG needs ``scale=4095``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from odmv.io.exr import ExrError, read_exr

#: Extensions read, in the order a view's file is looked for.
IMAGE_EXTENSIONS = (".exr", ".png", ".tif", ".tiff", ".bmp", ".npy")
FITS = ("resize", "crop", "pad")


class ImageError(ValueError):
    """A one-line error naming the image file and its problem."""


@dataclass(frozen=True)
class Image:
    """A single-channel image as stored (``data``) and its full-scale value."""

    data: np.ndarray
    full_scale: float
    kind: str  # how the values were stored, e.g. "16-bit integers"


def read_image(path: str | Path) -> Image:
    """One single-channel image; a colour image is refused (intensity must stay linear)."""
    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        try:
            channels = read_exr(path)
        except ExrError as e:
            raise ImageError(str(e)) from None
        if "Y" in channels:
            data = channels["Y"]
        elif len(channels) == 1:
            data = next(iter(channels.values()))
        else:
            raise ImageError(f"{path}: channels {sorted(channels)}, none named 'Y'")
        return Image(data.astype(np.float32), 1.0, "float EXR")
    if suffix == ".npy":
        try:
            data = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise ImageError(f"{path}: not a readable .npy array ({e})") from None
    elif suffix in IMAGE_EXTENSIONS:
        from PIL import Image as PILImage
        from PIL import UnidentifiedImageError

        try:
            with PILImage.open(path) as im:
                data = np.array(im)
        except (UnidentifiedImageError, OSError) as e:
            raise ImageError(f"{path}: not a readable image ({e})") from None
    else:
        raise ImageError(f"{path}: unknown image type (use {', '.join(IMAGE_EXTENSIONS)})")
    data = np.squeeze(data)
    if data.ndim == 3:
        colour = data[..., :3] if data.shape[-1] >= 3 else data[..., :1]  # alpha aside
        if not all(np.array_equal(colour[..., 0], colour[..., c]) for c in range(colour.shape[-1])):
            raise ImageError(
                f"{path}: a colour image; give the camera's single-channel (linear) image"
            )
        data = data[..., 0]
    if data.ndim != 2:
        raise ImageError(f"{path}: shape {data.shape} is not a single-channel image")
    if data.dtype == np.uint8:
        return Image(data.astype(np.float32), 255.0, "8-bit integers")
    if data.dtype == np.uint16 or (data.dtype == np.int32 and suffix != ".npy"):
        # Pillow returns some 16-bit PNG and TIFF files as 32-bit integers
        return Image(data.astype(np.float32), 65535.0, "16-bit integers")
    if np.issubdtype(data.dtype, np.floating):
        return Image(data.astype(np.float32), 1.0, "floats")
    raise ImageError(f"{path}: values of type {data.dtype}; use 8/16-bit integers or floats")


#: an image holds a fringe when its intensity spreads (1st to 99th percentile) by at least this
#: share of its bright level (99th percentile): a fringe spreads by most of it (~0.9), a flat
#: grey or saturated capture only by its noise; and when that level is at least DARK_LEVEL of
#: full scale (a black frame is all noise). Relative, so a dim capture (12-bit values read as
#: 16-bit, a weak projector) still counts.
MIN_FRINGE_CONTRAST = 0.1
DARK_LEVEL = 0.01
#: below this no data are an intensity at all (what a corrupted file decodes to)
NO_INTENSITY_BELOW = -1.01


def intensity_problem(
    path: Path,
    a: np.ndarray,
    negative: str,
    bright: str,
    fringe: bool = False,
    floor: float = -0.01,
) -> str | None:
    """What is wrong with an image of linear intensity in full-scale units, or None: values
    that are not finite, below ``floor`` (``negative`` says what to do; a capture's dark
    subtraction may dip just below zero; below -1 no data are intensity at all), above 1.5 on
    more than 1 % of the pixels (``bright`` says what to do), or, for a fringe image
    (``fringe``), no fringe at all."""
    bad = int((~np.isfinite(a)).sum())
    if bad:
        return f"{path}: {bad} pixel(s) are not finite (NaN or infinite)"
    lo, hi = float(a.min(initial=0)), float(a.max(initial=0))
    if lo < NO_INTENSITY_BELOW:
        return (
            f"{path}: intensities down to {lo:.3g}, which no camera records (a corrupted or "
            "foreign file?); capture, render or convert it again"
        )
    if lo < floor:
        return f"{path}: fringe intensities in [{lo:.3g}, {hi:.3g}] are negative; {negative}"
    share = float((a > 1.5).mean())
    if share > 0.01:
        return (
            f"{path}: {share:.1%} of the intensities lie above 1.5 times full scale (range "
            f"[{lo:.3g}, {hi:.3g}]); {bright}"
        )
    return fringe_problem(path, a) if fringe else None


def fringe_problem(path, a: np.ndarray) -> str | None:
    """The line saying an image where a projector's fringe belongs holds none (black, one grey
    level or saturated: MIN_FRINGE_CONTRAST, DARK_LEVEL), or None."""
    low, high = (float(x) for x in np.percentile(a, [1, 99]))
    if high < DARK_LEVEL or high - low < MIN_FRINGE_CONTRAST * high:
        return (
            f"{path}: no fringe (1-99 % intensities {low:.3f}-{high:.3f} of full scale): a "
            "uniform, black or saturated image where the projector's fringe belongs"
        )
    return None


def fit_to(stack: np.ndarray, size: tuple[int, int], fit: str) -> tuple[np.ndarray, str]:
    """Bring S x h x w images to the network's ``size`` (H, W); returns them and what was done.

    ``resize`` scales the whole image (area averaging; the aspect may change), ``crop`` keeps
    the central part with the network's aspect, ``pad`` adds dark borders up to that aspect;
    crop and pad then scale."""
    if fit not in FITS:
        raise ImageError(f"fit: {fit!r} unknown; choose {', '.join(FITS)}")
    h, w = stack.shape[-2:]
    H, W = size
    if (h, w) == (H, W):
        return stack, f"{w}x{h}, the network's size"
    note = f"{w}x{h} -> {W}x{H} by {fit}"
    if fit == "crop":
        ch, cw = (h, round(h * W / H)) if w * H > h * W else (round(w * H / W), w)
        top, left = (h - ch) // 2, (w - cw) // 2
        stack = stack[:, top : top + ch, left : left + cw]
        note += f" (central {cw}x{ch})"
    elif fit == "pad":
        ph, pw = (round(w * H / W), w) if w * H > h * W else (h, round(h * W / H))
        out = np.zeros((stack.shape[0], ph, pw), np.float32)
        top, left = (ph - h) // 2, (pw - w) // 2
        out[:, top : top + h, left : left + w] = stack
        stack = out
        note += f" (padded to {pw}x{ph})"
    elif h * W != w * H:
        note += " (aspect changed)"
    t = torch.from_numpy(np.ascontiguousarray(stack, np.float32))[None]
    return torch.nn.functional.interpolate(t, size=(H, W), mode="area")[0].numpy(), note


def find_view_image(folder: Path, stem: str) -> Path | None:
    """``folder/stem.<ext>`` for the first extension present (IMAGE_EXTENSIONS order)."""
    for ext in IMAGE_EXTENSIONS:
        for name in (stem + ext, stem + ext.upper()):
            if (folder / name).is_file():
                return folder / name
    return None
