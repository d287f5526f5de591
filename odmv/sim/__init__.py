"""The digital twin: procedural scenes (:mod:`~odmv.sim.scenes`), ray-cast rendering of the
four-projector rig (:mod:`~odmv.sim.render`), the shifts a real rig differs by
(:mod:`~odmv.sim.shifts`), and datasets written to the contract, whole or in shards
(:mod:`~odmv.sim.writer`, :mod:`~odmv.sim.shards`)."""
