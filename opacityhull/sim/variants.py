"""Choosing the Mitsuba variant: ``llvm_ad_rgb`` when it works here, else ``scalar_rgb``.

A Dr.Jit LLVM backend linked against an old libLLVM (Debian's 14–16) *aborts the
interpreter* the first time it compiles a kernel (``LLVM ERROR: Cannot select``), which
no ``try`` can catch (PITFALLS). So the LLVM variant is first tried in a child process
that renders a 4×4 image; only if that child exits cleanly is the variant used here.
The probe's verdict is cached in ``~/.cache/opacityhull/mitsuba-variant.json`` keyed by
the Mitsuba and Dr.Jit versions, the Python executable and ``DRJIT_LIBLLVM_PATH``, so
it costs ~1 s once per machine rather than once per process.

``OPACITYHULL_MITSUBA_VARIANT`` (e.g. ``scalar_rgb``) overrides the choice without a
probe. Both variants give the same images up to Monte-Carlo noise; tests pass with
either.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
from pathlib import Path

from ..errors import ConfigError

__all__ = ["choose_variant", "probe_variant", "use_mitsuba", "ENV_VARIANT", "SUPPORTED_VARIANTS"]

ENV_VARIANT = "OPACITYHULL_MITSUBA_VARIANT"
SUPPORTED_VARIANTS = ("llvm_ad_rgb", "scalar_rgb")
_PREFERRED = "llvm_ad_rgb"
_FALLBACK = "scalar_rgb"

_PROBE_SCRIPT = r"""
import sys
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "direct"},
    "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 4, "height": 4,
                                               "rfilter": {"type": "box"}}},
    "shape": {"type": "sphere", "center": [0, 0, 3]},
    "light": {"type": "point", "position": [0, 0, 0]},
})
import numpy as np
img = np.array(mi.render(scene, spp=1))
assert img.shape[:2] == (4, 4) and np.isfinite(img).all() and img.max() > 0
print("OK")
"""

_lock = threading.Lock()
_chosen: str | None = None


def _cache_file() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "opacityhull" / "mitsuba-variant.json"


def _cache_key() -> str:
    try:
        from importlib.metadata import version

        mv, dv = version("mitsuba"), version("drjit")
    except Exception:  # pragma: no cover - metadata missing in odd installs
        mv = dv = "?"
    return "|".join([mv, dv, sys.executable, os.environ.get("DRJIT_LIBLLVM_PATH", "")])


def probe_variant(variant: str, *, timeout_s: float = 120.0) -> bool:
    """Render a 4×4 image with ``variant`` in a child process; True if it exited cleanly.

    A crash (SIGABRT from a wrong libLLVM), a non-zero exit or a timeout count as
    "does not work"; nothing in this process is touched.
    """
    try:
        r = subprocess.run(
            [sys.executable, "-c", _PROBE_SCRIPT, variant],
            capture_output=True,
            text=True,
            timeout=timeout_s,
        )
    except (subprocess.TimeoutExpired, OSError):
        return False
    return r.returncode == 0 and "OK" in r.stdout


def choose_variant(*, refresh: bool = False) -> str:
    """The Mitsuba variant this process should use (``llvm_ad_rgb`` or ``scalar_rgb``).

    Order: the ``OPACITYHULL_MITSUBA_VARIANT`` environment variable; the cached probe
    result for this installation; a fresh probe of ``llvm_ad_rgb`` in a subprocess
    (cached afterwards). ``refresh=True`` ignores the cache file.

    Raises
    ------
    ConfigError
        The environment variable names a variant that is not supported.
    """
    global _chosen
    env = os.environ.get(ENV_VARIANT, "").strip()
    if env:
        if env not in SUPPORTED_VARIANTS:
            raise ConfigError(f"{ENV_VARIANT}={env!r}: expected one of {list(SUPPORTED_VARIANTS)}")
        return env
    with _lock:
        if _chosen is not None and not refresh:
            return _chosen
        key = _cache_key()
        path = _cache_file()
        if not refresh:
            try:
                data = json.loads(path.read_text())
                if data.get("key") == key and data.get("variant") in SUPPORTED_VARIANTS:
                    _chosen = data["variant"]
                    return _chosen
            except (OSError, ValueError):
                pass
        variant = _PREFERRED if probe_variant(_PREFERRED) else _FALLBACK
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}")
            tmp.write_text(json.dumps({"key": key, "variant": variant}))
            os.replace(tmp, path)
        except OSError:
            pass  # a read-only home only costs a probe per process
        _chosen = variant
        return variant


def use_mitsuba(variant: str | None = None):
    """Import Mitsuba, set the chosen (or given) variant, return the ``mitsuba`` module.

    The variant is process-global in Mitsuba; once one is set, later calls with
    ``variant=None`` keep it.
    """
    import mitsuba as mi

    current = mi.variant()
    if variant is None:
        if current in SUPPORTED_VARIANTS:
            return mi
        variant = choose_variant()
    if variant not in SUPPORTED_VARIANTS:
        raise ConfigError(f"Mitsuba variant {variant!r}: expected one of {list(SUPPORTED_VARIANTS)}")
    if current != variant:
        mi.set_variant(variant)
    return mi
