"""opacityhull — image-based 3D photography with opacity hulls.

Stages meet only through on-disk formats (:mod:`opacityhull.session`,
:mod:`opacityhull.model`) and the shared core (:mod:`opacityhull.camera`,
:mod:`opacityhull.imageio`). See ARCHITECTURE.md.
"""

__version__ = "0.1.0"
