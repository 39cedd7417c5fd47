"""Choosing the Mitsuba variant: ``cuda_ad_rgb`` where a GPU runs it, else
``llvm_ad_rgb`` when it works here, else ``scalar_rgb``.

The CUDA variant is probed first, in a child process like the LLVM one (without a GPU
or driver it fails there — nothing changes here — and the verdict is cached); where it
renders, it is used.

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

__all__ = [
    "choose_variant",
    "select_variant",
    "variant_report",
    "probe_variant",
    "use_mitsuba",
    "ENV_VARIANT",
    "SUPPORTED_VARIANTS",
]

ENV_VARIANT = "OPACITYHULL_MITSUBA_VARIANT"
SUPPORTED_VARIANTS = ("cuda_ad_rgb", "llvm_ad_rgb", "scalar_rgb")
#: Probed in this order; the first that renders is chosen. ``scalar_rgb`` always works.
_PROBE_ORDER = ("cuda_ad_rgb", "llvm_ad_rgb")
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
_report: dict | None = None


def _cache_file() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "opacityhull" / "mitsuba-variant.json"


def _cache_key() -> str:
    try:
        from importlib.metadata import version

        mv, dv = version("mitsuba"), version("drjit")
    except ImportError:  # pragma: no cover - metadata missing in odd installs (PackageNotFoundError)
        mv = dv = "?"
    # "v2": the probe order gained cuda_ad_rgb; older files (LLVM only) are re-probed once
    return "|".join(["v2", mv, dv, sys.executable, os.environ.get("DRJIT_LIBLLVM_PATH", "")])


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


def select_variant(probe) -> tuple[str, dict[str, bool]]:
    """The first variant of ``cuda_ad_rgb``, ``llvm_ad_rgb`` for which ``probe(variant)``
    is true, else ``scalar_rgb``; and the probe verdicts taken (pure: ``probe`` is
    :func:`probe_variant` in use, a fake in tests)."""
    verdicts: dict[str, bool] = {}
    for v in _PROBE_ORDER:
        verdicts[v] = bool(probe(v))
        if verdicts[v]:
            return v, verdicts
    return _FALLBACK, verdicts


def choose_variant(*, refresh: bool = False) -> str:
    """The Mitsuba variant this process should use (``cuda_ad_rgb``, ``llvm_ad_rgb`` or
    ``scalar_rgb``).

    Order: the ``OPACITYHULL_MITSUBA_VARIANT`` environment variable; the cached probe
    result for this installation; fresh probes in a subprocess — ``cuda_ad_rgb``, then
    ``llvm_ad_rgb`` (:func:`select_variant`; cached afterwards). ``refresh=True`` ignores
    the cache file. :func:`variant_report` says how the choice was made.

    Raises
    ------
    ConfigError
        The environment variable names a variant that is not supported.
    """
    global _chosen, _report
    env = os.environ.get(ENV_VARIANT, "").strip()
    if env:
        if env not in SUPPORTED_VARIANTS:
            raise ConfigError(f"{ENV_VARIANT}={env!r}: expected one of {list(SUPPORTED_VARIANTS)}")
        _report = {"variant": env, "source": f"environment {ENV_VARIANT}", "probes": {}}
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
                    chosen = _chosen = str(data["variant"])
                    _report = {
                        "variant": chosen,
                        "source": f"cached probe {path}",
                        "probes": dict(data.get("probes", {})),
                    }
                    return chosen
            except (OSError, ValueError):
                pass
        # look the probe up at call time: tests replace it with a fake
        variant, verdicts = select_variant(lambda v: probe_variant(v))
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}")
            tmp.write_text(json.dumps({"key": key, "variant": variant, "probes": verdicts}))
            os.replace(tmp, path)
        except OSError:
            pass  # a read-only home only costs a probe per process
        _chosen = variant
        _report = {"variant": variant, "source": "probed in a subprocess", "probes": verdicts}
        return variant


def variant_report() -> dict:
    """How :func:`choose_variant` chose: ``{"variant", "source", "probes"}`` (probes:
    variant → rendered in the probe; a GPU shows as ``"cuda_ad_rgb": true``)."""
    v = choose_variant()
    rep = (
        dict(_report)
        if _report is not None and _report.get("variant") == v
        else {"variant": v, "source": "chosen earlier in this process", "probes": {}}
    )
    rep["gpu"] = v.startswith("cuda")
    return rep


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
