"""Training a net: the LightningModule (:mod:`~odmv.training.module`), the composite loss
and mm metrics, the weights' moving average, checkpoints, the run folder's lock, the
provenance a run records, the CPU pace notes, the resumable CSV logger, the sweep's results
table, and the benchmark scripts' shared setup (:mod:`~odmv.training.bench`)."""
