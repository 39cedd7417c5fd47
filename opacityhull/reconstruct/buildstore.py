"""The build's step manifest (``MODEL/build/manifest.json``), the digests of a step's
inputs, and :func:`cached`: the one reuse-or-run protocol every build step goes through."""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar, cast
from collections.abc import Callable, Sequence

import numpy as np

from ..camera import Camera
from ..errors import FormatError
from ..model import BUILD_DIR
from ..session import Session
from .matte_step import _jsonable

log = logging.getLogger(__name__)

BUILD_FORMAT = "opacityhull.build/1"

#: BuildConfig fields that do not change a step's product (everything else does: a
#: step is stale when any other field differs, which errs on the side of redoing)
_NOT_GEOMETRY = (
    "reflectance",
    "pictures",
    "natural",
    "natural_kernels",
    "verify_checksums",
    "ground_truth_dilate_px",
    "alpha_eps",
    "storage",  # the pixel type of the written files: only the write step depends on it
    "reflectance_storage",  # likewise how the reflectance files are written
    "pca_rank",
    "pca_error",
    "pca_block",
    "optimize",  # the fit runs on the written model, after the geometry
    "optimize_iterations",
)


#: keys of a product's dicts that hold wall-clock figures (the photo refinement's and the
#: natural field's ``seconds``, the calibration's stage seconds are a whole dict): they
#: are popped before a product is pickled and go to ``report.json`` only, the one file of
#: a model that records this run's times (#35: two builds repeat byte for byte elsewhere)
TIMING_KEYS = ("seconds", "seconds_cost_volume", "pixels_per_s")


def pop_timings(d: dict, keys: Sequence[str] = TIMING_KEYS) -> dict:
    """The wall-clock entries ``keys`` of ``d``, removed from it (in place)."""
    return {k: d.pop(k) for k in keys if k in d}


def _digest(obj) -> str:
    """SHA-256 of a JSON-able structure (sorted keys): the identity of a step's inputs."""
    import hashlib

    return hashlib.sha256(json.dumps(_jsonable(obj), sort_keys=True, default=repr).encode()).hexdigest()


def _camera_digest(cam: Camera) -> str:
    import hashlib

    h = hashlib.sha256()
    for a in (cam.K, cam.dist, cam.world_from_cam):
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    h.update(f"{cam.width}x{cam.height}".encode())
    return h.hexdigest()


def _records_digest(session: Session, recs) -> list:
    """What identifies the images a step read: manifest id, sha256 and size, and the
    file's size and mtime (a file replaced behind the manifest's back is stale too)."""
    out = []
    for r in recs:
        try:
            st = (session.root / r.path).stat()
            fs = [st.st_size, st.st_mtime_ns]
        except OSError:
            fs = None
        out.append([r.id, r.sha256, r.bytes, fs])
    return out


def _files_digest(root: Path) -> list:
    if not root.is_dir():
        return []
    out = []
    for p in sorted(root.rglob("*")):
        if p.is_file():
            st = p.stat()
            out.append([str(p.relative_to(root)), st.st_size, st.st_mtime_ns])
    return out


#: files up to this size are digested whole (sha256); larger ones by size, mtime and the
#: sha256 of their first and last MiB. Measured (``benchmarks/build_digest.py``, 2 cores
#: shared by 8 jobs): sha256 reads ~500 MB/s, so a dinoSR model's views and surfels.ply
#: (17 files, 24 MB) take 45 ms and 48 views of 640x480 half RGBA plus 300 k surfels
#: (127 MB) 0.26 s — cheap next to any step a resume skips. Only a single file past
#: 256 MiB (none of the models built today) takes the cheap path.
FULL_DIGEST_MAX_BYTES = 256 << 20
_EDGE_BYTES = 1 << 20


def file_digest(path: Path) -> str:
    """What a product file must still be for a resume to reuse it: ``sha256:HEX`` of its
    bytes, or, past :data:`FULL_DIGEST_MAX_BYTES`, ``edges:SIZE:MTIME_NS:HEX`` (the sha256
    of its first and last MiB). Raises OSError when it cannot be read."""
    import hashlib

    st = path.stat()
    h = hashlib.sha256()
    with open(path, "rb") as f:
        if st.st_size <= FULL_DIGEST_MAX_BYTES:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
            return "sha256:" + h.hexdigest()
        h.update(f.read(_EDGE_BYTES))
        f.seek(max(0, st.st_size - _EDGE_BYTES))
        h.update(f.read(_EDGE_BYTES))
    return f"edges:{st.st_size}:{st.st_mtime_ns}:{h.hexdigest()}"


def _output_files(root: Path, outputs: Sequence[str]) -> list[str]:
    """The files an output list names (folders expanded), relative to ``root``."""
    files = []
    for o in outputs:
        p = root / o
        if p.is_dir():
            files += sorted(str(q.relative_to(root)) for q in p.rglob("*") if q.is_file())
        else:
            files.append(str(o))
    return files


class _StepStore:
    """The build's step manifest (``MODEL/build/manifest.json``): per finished step, the
    digest of its inputs (images' sha256/mtimes, upstream steps) and parameters, its
    outputs and each output file's digest when written (:func:`file_digest`). With
    ``resume`` a step whose key matches and whose outputs are still what it wrote is
    reused; a changed, missing or unreadable output makes it run again, with a note."""

    def __init__(self, model_dir: Path, *, resume: bool):
        self.model_dir = model_dir
        self.dir = model_dir / BUILD_DIR
        self.path = self.dir / "manifest.json"
        self.resume = resume
        self.steps: dict = {}
        #: step name -> "ran" | "reused" | "reused k of n views" (the report's ``steps``)
        self.status: dict[str, str] = {}
        #: why a step that could have been reused ran again (for the report's notes)
        self.notes: list[str] = []
        if resume and self.path.is_file():
            try:
                d = json.loads(self.path.read_text())
            except (OSError, ValueError) as e:
                raise FormatError(
                    f"{self.path}: unreadable build manifest ({e}); delete {self.dir} or build without --resume"
                ) from None
            if not isinstance(d, dict) or d.get("format") != BUILD_FORMAT or not isinstance(d.get("steps"), dict):
                raise FormatError(
                    f"{self.path}: not an {BUILD_FORMAT} manifest (format "
                    f"{d.get('format') if isinstance(d, dict) else d!r}); delete {self.dir} or build "
                    "without --resume"
                )
            self.steps = dict(d["steps"])

    def _stale(self, name: str, why: str) -> bool:
        msg = f"build step {name}: {why}; the step runs again"
        log.warning("%s", msg)
        self.notes.append(msg)
        return False

    def fresh(self, name: str, key: str) -> bool:
        """Whether step ``name`` with input key ``key`` can be reused: resuming, the same
        key, and every output file there with the digest it was written with."""
        e = self.steps.get(name)
        if not (self.resume and isinstance(e, dict) and e.get("key") == key):
            return False
        digests = e.get("digests")
        if not isinstance(digests, dict):
            return all((self.model_dir / o).exists() for o in e.get("outputs", []))
        for o in e.get("outputs", []):
            if not (self.model_dir / o).exists():
                return self._stale(name, f"{o} is missing")
        for rel, want in digests.items():
            try:
                got = file_digest(self.model_dir / rel)
            except OSError as err:
                return self._stale(name, f"{rel} cannot be read ({err.strerror or err})")
            if got != want:
                return self._stale(name, f"{rel} changed since it was written (digest mismatch)")
        return True

    def record(
        self,
        name: str,
        key: str,
        *,
        inputs: dict,
        params: dict,
        outputs: Sequence[str],
        status: str = "ran",
        digest_outputs: bool = True,
    ) -> None:
        from ..imageio import atomic_path

        entry = {
            "key": key,
            "inputs": inputs,
            "params": params,
            "outputs": list(outputs),
        }
        if digest_outputs:
            entry["digests"] = {
                rel: file_digest(self.model_dir / rel) for rel in _output_files(self.model_dir, outputs)
            }
        self.steps[name] = entry
        self.status[name] = status
        self.dir.mkdir(parents=True, exist_ok=True)
        with atomic_path(self.path) as tmp:
            tmp.write_text(json.dumps(_jsonable({"format": BUILD_FORMAT, "steps": self.steps}), indent=1) + "\n")

    def reuse(self, name: str, status: str = "reused") -> None:
        self.status[name] = status

    def save(self, rel: str, obj) -> str:
        import pickle

        from ..imageio import atomic_path

        # streamed: a hull grid and silhouettes of hundreds of views are not copied into
        # one bytes object first
        with atomic_path(self.model_dir / rel) as tmp, open(tmp, "wb") as f:
            pickle.dump(obj, f, protocol=pickle.HIGHEST_PROTOCOL)
        return rel

    def load(self, rel: str):
        """The pickled product, or None when it cannot be read back (then the step runs)."""
        import pickle

        try:
            with open(self.model_dir / rel, "rb") as f:
                return pickle.load(f)
        except Exception as e:  # noqa: BLE001  (unpickling bytes that are not ours may raise anything)
            self.notes.append(f"{rel}: cannot be read back ({type(e).__name__}: {e}); its step runs again")
            log.warning("%s: cannot reuse (%s); the step runs again", self.model_dir / rel, e)
            return None


T = TypeVar("T")


@dataclass(frozen=True)
class Cached(Generic[T]):
    """What :func:`cached` gives back: the product, the step's key and whether it was reused."""

    value: T
    key: str
    reused: bool


def cached(
    store: _StepStore,
    name: str,
    *,
    inputs: dict,
    params: dict,
    run: Callable[[], T],
    pickle_as: str | None = None,
    expect: type | tuple | Callable[[Any], bool] | None = None,
    outputs: Sequence[str] | Callable[[T], Sequence[str]] = (),
    on_reuse: Callable[[dict], T] | None = None,
    reuse: bool = True,
    status: Callable[[T], str] | None = None,
    key: str | None = None,
) -> Cached[T]:
    """The one reuse-or-run protocol of the build's steps.

    The step's key is the digest of ``inputs`` (digests of images and upstream keys) and
    ``params`` (the options that shape the product), unless ``key`` is given. When
    resuming and :meth:`_StepStore.fresh` (same key, outputs as written), the product is
    reused: unpickled from ``pickle_as`` (``build/NAME.pkl``) and checked to be an
    ``expect`` instance, or made by ``on_reuse(manifest entry)``, or None. Otherwise —
    or when the pickle cannot be read back or is of the wrong type, which is noted —
    ``run()`` makes it, it is pickled to ``pickle_as``, and the manifest records the key,
    inputs, params, the outputs (``pickle_as`` plus ``outputs``, or ``outputs(product)``)
    and each output file's digest. ``reuse=False``: the step does its own per-item reuse
    (matting), and is only recorded; ``status(product)`` then says how much was reused.
    """
    if key is None:
        key = _digest({"inputs": inputs, "params": params})
    if reuse and store.fresh(name, key):
        if pickle_as is not None:
            got = store.load(pickle_as)
            ok = expect is None or (isinstance(got, expect) if isinstance(expect, (type, tuple)) else expect(got))
            if got is not None and ok:
                store.reuse(name)
                return Cached(got, key, True)
            if got is not None:
                store.notes.append(
                    f"{pickle_as}: holds a {type(got).__name__}, not the {name} step's product; the step runs again"
                )
        else:
            store.reuse(name)
            e = store.steps.get(name, {})
            return Cached(cast(T, on_reuse(e) if on_reuse is not None else None), key, True)
    value = run()
    outs = list(outputs(value) if callable(outputs) else outputs)
    if pickle_as is not None:
        store.save(pickle_as, value)
        outs = [pickle_as, *outs]
    store.record(
        name,
        key,
        inputs=inputs,
        params=params,
        outputs=outs,
        status=status(value) if status is not None else "ran",
        digest_outputs=reuse,
    )
    return Cached(value, key, False)
