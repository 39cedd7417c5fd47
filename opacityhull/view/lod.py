"""Re-export of :mod:`opacityhull.render.lod` (the sequential point tree moved to
``render`` so that ``render --budget`` can use it; ``render`` must not import ``view``)."""

from ..render.lod import *  # noqa: F401,F403
from ..render.lod import __all__  # noqa: F401
