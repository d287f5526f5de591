"""Import FPP datasets into the odmv dataset contract:
``python -m odmv.convert format=NAME src=PATH out=PATH``.

Formats (``format=NAME``; each one entry of odmv.importers.formats.FORMATS; docs/dataset.md,
"Importing datasets" and "A dataset from your own rig"): ``nguyen2020``, ``uhrnet`` (height
maps), ``fppmlbench``, ``folder`` (``src/<scene>/<view>.<ext>`` and a depth map per scene) and
``sequences`` (each projector's phase-shifting sequences named by ``psp.*``, with
``calibration=FILE`` or ``manifest=DATASET``: the ground truth is their classical
reconstruction and the full sequences are kept). What the dataset holds: odmv.importers.convert.
"""

from __future__ import annotations

from omegaconf import DictConfig

from odmv.classical.sequences import PspOptions
from odmv.cli import run_app
from odmv.config import app
from odmv.importers.convert import convert
from odmv.importers.formats import FORMATS


@app("convert")
def main(cfg: DictConfig) -> None:
    options = {k: v for k, v in (cfg.options or {}).items()}

    def run():
        entry = FORMATS.get(cfg.format)
        psp = PspOptions.from_cfg(cfg.psp) if entry is not None and entry.rig else None
        return convert(
            cfg.format, cfg.src, cfg.out, cfg.intensity, cfg.calibration, psp, cfg.manifest,
            **options,
        )  # fmt: skip

    m = run_app(run)
    counts = {s: sum(x["split"] == s for x in m.scenes) for s in ("train", "val", "test")}
    print(
        f"{m.root}: {len(m.scenes)} scenes ({counts['train']} train, {counts['val']} val, "
        f"{counts['test']} test), {m.width_px}x{m.height_px} px, views {', '.join(m.views)}; "
        f"check it with python -m odmv.validate {m.root}"
    )


if __name__ == "__main__":
    main()
