"""flightsim.render: the simulated camera — grey frames and per-pixel depth of a world, through
the companion's own camera model (intrinsics, OpenCV distortion, mount).  See
:mod:`.renderer` for the method (:mod:`.solids` draws the obstacles) and :mod:`.bench` for the speed
benchmark."""

from .renderer import Frame, Renderer, RenderOptions

__all__ = ["Frame", "RenderOptions", "Renderer"]
