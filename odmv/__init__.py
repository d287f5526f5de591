"""odmv: multi-view fringe projection profilometry with deep networks."""

__version__ = "0.1.0"
