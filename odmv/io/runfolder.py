"""The files of a run folder, named once. A finished run (``python -m odmv.train``, the
classical row, or a reproduction's record of one) holds ``metrics.json`` (its test metrics,
settings and provenance) and, where they were written or kept: ``heldout.json`` (its scores on
the held-out set), ``robustness.json`` (its scores on shifted twins of its dataset),
``test_scenes.csv`` (per-scene errors), ``test_predictions.npz`` (predicted
and true depth in mm), ``.hydra/config.yaml`` and ``checkpoints/``. How runs are found and read:
:mod:`odmv.study.records`."""

METRICS = "metrics.json"
HELDOUT = "heldout.json"
SCENES_CSV = "test_scenes.csv"
PREDICTIONS = "test_predictions.npz"
CONFIG = ".hydra/config.yaml"
ROBUSTNESS = "robustness.json"
