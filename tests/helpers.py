"""Small builders shared by the test files (``tests/`` is on ``sys.path`` through
``tests/conftest.py``; benchmarks that import test modules add it themselves).

The camera-entry builders of rig-geometry dicts are here; the two display panels of the
lab layout are :func:`opacityhull.riggeometry.bottom_display` and ``back_display``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any
from collections.abc import Callable


def python_child(script: Path, *args: str, env: dict[str, str], preexec_fn: Callable[[], Any] | None = None):
    """Start ``python SCRIPT ARGS...`` with text pipes on stdout and stderr, in the
    environment ``env`` (a full environment, e.g. ``os.environ`` plus keys); returns the
    :class:`subprocess.Popen`."""
    cmd = [sys.executable, str(script), *map(str, args)]
    return subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, preexec_fn=preexec_fn
    )


def with_pythonpath(folder: Path) -> dict[str, str]:
    """``os.environ`` with ``folder`` first on ``PYTHONPATH``."""
    return dict(os.environ, PYTHONPATH=str(folder) + os.pathsep + os.environ.get("PYTHONPATH", ""))


def fill_with_zeros(path: Path) -> None:
    """Write 64 KiB blocks of zeros to the file ``path`` until the file system refuses
    (ENOSPC or a quota); the error is the point, so it is swallowed."""
    with open(path, "wb", buffering=0) as f:
        try:
            while True:
                f.write(b"\0" * 65536)
        except OSError:
            pass


def camera_spec(name: str, width: int, height: int, **fields: Any) -> dict[str, Any]:
    """A ``[[cameras]]`` entry of a rig-geometry dict: ``width`` x ``height`` px, plus
    ``fields`` (``distance_m``, ``elevation_deg``, ``fov_y_deg``, ...) as given."""
    return {"name": name, "width": width, "height": height, **fields}


def ring_cameras(width: int, height: int, elevations_azimuths_deg, **fields: Any) -> list[dict[str, Any]]:
    """``cam0``, ``cam1``, ... at the given (elevation, azimuth) pairs in degrees, all
    ``width`` x ``height`` px with the same ``fields`` (``distance_m``, ``focal_px``, ...)."""
    return [
        camera_spec(f"cam{i}", width, height, **fields, elevation_deg=el, azimuth_deg=az)
        for i, (el, az) in enumerate(elevations_azimuths_deg)
    ]


def invoke_cli(argv):
    """Run the real CLI app in-process on ``argv`` (paths and numbers are passed as
    ``str``); returns the click Result (stdout and stderr apart)."""
    from typer.testing import CliRunner

    from opacityhull.cli import app, normalize_argv

    # a wide terminal: rich would otherwise break long paths inside the messages
    return CliRunner().invoke(app, normalize_argv([str(a) for a in argv]), env={"COLUMNS": "4000"})


def load_viewer(drv, url: str) -> dict:
    """Open the viewer page at ``url`` in the WebDriver ``drv``; its ready record (``ok``, ``error``)."""
    from opacityhull.view.browser import wait_ready

    drv.get(url)
    return wait_ready(drv, timeout_s=90)


def viewer_error(drv, bundle: Path) -> str:
    """Serve the bundle folder, load the viewer, check that it fails and shows an error; the error's text."""
    from opacityhull.view.server import BundleServer

    with BundleServer(bundle) as srv:
        r = load_viewer(drv, srv.url)
        assert not r["ok"]
        error = drv.find_element("id", "error")
        assert error.is_displayed()
        return error.text


def copy_without(src: Path, dst: Path, *missing: str) -> Path:
    """``dst``: a copy of the folder ``src`` without the files named ``missing`` (relative paths)."""
    import shutil

    shutil.copytree(src, dst)
    for name in missing:
        (dst / name).unlink()
    return dst
