"""opacityhull — image-based 3D photography with opacity hulls.

Stages meet only through on-disk formats (:mod:`opacityhull.session`,
:mod:`opacityhull.model`) and the shared core (:mod:`opacityhull.camera`,
:mod:`opacityhull.imageio`). See ARCHITECTURE.md.
"""

import os as _os

# numba's threading layer here is OpenMP, whose idle threads spin by default. With other
# processes on the cores, the spinning thread steals the time its partner needs: 60 fit
# steps took 208 ms each on two threads against 26 ms on one. PASSIVE makes idle threads
# sleep; on an idle machine it costs nothing (benchmarks/optimize_raster.py, 300 k
# surfels at 400×400: 97 ms spinning, 96 ms passive). It must be set before the OpenMP
# runtime starts (numba's first parallel call), and a user's own setting wins.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
