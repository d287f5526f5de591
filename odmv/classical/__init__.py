"""Fringe analysis without a network: phase shifting and Fourier-transform profilometry,
unwrapping and triangulation (:mod:`~odmv.classical.fringe`), the rig's triangulation as
per-pixel maps and a torch layer (:mod:`~odmv.classical.geometry`), the sequences rigs save
(:mod:`~odmv.classical.sequences`), and the classical method on one scene's images, from the
full sequences down to one image per projector (:mod:`~odmv.classical.reconstruct`)."""
