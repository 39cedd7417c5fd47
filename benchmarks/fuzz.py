"""Fuzzing pass (#35): hypothesis-driven mutations of every file format the project reads,
fed to the project's own readers in-process (and a sample through the CLI).

Formats: session.toml, manifest.jsonl, rig TOML, plan TOML, COLMAP text and binary,
transforms.json, EXR, HDR, PLY (surfels.ply), the viewer bundle (manifest.json and its
binary chunks). Mutations: truncation, bit flips, wrong types (a number replaced by a
string, list, table or boolean), huge sizes (1e308, 2**63, 0xFF.. u64 counts), NaN/Inf.

Each mutated input ends in one of:

- ``ok``: the reader returned (the mutation was harmless or the value is valid);
- ``named``: an opacityhull error (InputError/FormatError/...) whose message names the
  file or folder;
- ``unnamed``: an opacityhull error that does not name the file (a finding);
- ``crash``: any other exception — a traceback for the user (a finding).

The pass is clean when there are no ``unnamed`` and no ``crash`` outcomes. ``--quick``
(``make bench``) runs 20 inputs per format; the default runs 200 per format (≥ 2,000 in
all) plus 20 through the CLI. The report lists the counts per format and outcome, and
every finding with the exception and a reproducer (format, mutation).

    python benchmarks/fuzz.py [--quick] [--per-format N] [--json]
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from pathlib import Path
from collections.abc import Callable

import numpy as np

from benchkit import parser

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "reconstruct"))  # rcsynth

# ----------------------------------------------------------------------------- seeds


def make_seeds(work: Path) -> dict[str, Path]:
    """One valid instance of every format (small: the whole pass stays fast)."""
    import rcsynth

    from opacityhull.export.formats import export_model
    from opacityhull.imageio import write_hdr
    from opacityhull.render.synthetic import write_sphere_model
    from opacityhull.view.bundle import write_bundle

    s = work / "session"
    rcsynth.make_session(s, n_cams=2, n_angles=2, width=16, height=12, n_patterns=1, ss=1)
    m = work / "model"
    write_sphere_model(m, n_surfels=200, width=16, height=12, table_step_deg=90.0)
    export_model(m, "colmap", work / "colmap")
    export_model(m, "nerfstudio", work / "ns")
    # each file in a folder of its own: an input's folder is copied per mutated input
    for sub in ("hdr", "rig", "plan"):
        (work / sub).mkdir()
    write_hdr(work / "hdr" / "map.hdr", np.random.default_rng(0).random((8, 16, 3)).astype(np.float32))
    write_bundle(m, work / "bundle", relight=False)
    shutil.copy(ROOT / "examples" / "rig-emulated.toml", work / "rig" / "rig.toml")
    shutil.copy(ROOT / "opacityhull" / "acquire" / "plans" / "tiny.toml", work / "plan" / "plan.toml")
    return {"session": s, "model": m, "colmap": work / "colmap" / "sparse" / "0", "ns": work / "ns", "work": work}


# ------------------------------------------------------------------------- mutations

_NUM = re.compile(rb"(?<![\w.])-?\d+(\.\d+)?([eE][-+]?\d+)?(?![\w.])")
TEXT_VALUES = [b"nan", b"inf", b"1e308", b"-1", b"9223372036854775808", b'"x"', b"[]", b"{}", b"true", b"0", b"-0.0"]
JSON_VALUES = [b"NaN", b"Infinity", b"1e308", b"-1", b"9223372036854775808", b'"x"', b"[]", b"{}", b"true", b"null"]


def mutate(data: bytes, kind: str, draw, *, text: bool, json_like: bool) -> bytes:
    """``data`` changed by one mutation of ``kind``, its choices drawn by hypothesis."""
    from hypothesis import strategies as st

    n = len(data)
    if kind == "truncate":
        return data[: draw(st.integers(0, max(0, n - 1)))]
    if kind == "bitflip":
        b = bytearray(data)
        for _ in range(draw(st.integers(1, 8))):
            i = draw(st.integers(0, n - 1))
            b[i] ^= 1 << draw(st.integers(0, 7))
        return bytes(b)
    if kind in ("wrongtype", "huge", "nan") and text:
        nums = list(_NUM.finditer(data))
        if not nums:
            return data[: n // 2]
        m = nums[draw(st.integers(0, len(nums) - 1))]
        pool = JSON_VALUES if json_like else TEXT_VALUES
        if kind == "huge":
            pool = [b"1e308", b"9223372036854775808", b"100000000000"]
        elif kind == "nan":
            pool = [b"NaN", b"Infinity"] if json_like else [b"nan", b"inf", b"-inf"]
        return data[: m.start()] + draw(st.sampled_from(pool)) + data[m.end() :]
    # binary: overwrite 8 aligned bytes with a huge count, NaN or a negative value
    if n < 8:
        return data[:0]
    i = draw(st.integers(0, n // 8 - 1)) * 8
    word = {
        "huge": b"\xff" * 8,
        "nan": np.array([np.nan]).tobytes(),
        "wrongtype": np.array([-1.0]).tobytes(),
    }[kind]
    return data[:i] + word + data[i + 8 :]


KINDS = ("truncate", "bitflip", "wrongtype", "huge", "nan")

# --------------------------------------------------------------------------- readers


def _read_session(root: Path):
    from opacityhull.session import Session

    s = Session.open(root)
    for r in s.records[:3]:
        s.load_image(r)
    return s


def _read_colmap(d: Path):
    from opacityhull.colmapbin import read_colmap_checked

    return read_colmap_checked(d)  # as `import colmap` reads a model


def _import_ns(transforms: Path):
    from opacityhull.acquire.importers import import_nerfstudio

    out = Path(tempfile.mkdtemp(prefix="fuzz-ns-")) / "s"
    try:
        return import_nerfstudio(transforms, out)
    finally:
        shutil.rmtree(out.parent, ignore_errors=True)


def _read_bundle(d: Path):
    from opacityhull.view.bundle import read_bundle

    return read_bundle(d)


def _read_model_ply(p: Path):
    from opacityhull.model import read_surfels_ply

    return read_surfels_ply(p)


def formats(seeds: dict[str, Path]) -> dict[str, tuple[Path, Path, Callable, bool, bool]]:
    """name → (folder copied per input, file mutated in it, reader(folder copy), text, json)."""
    from opacityhull.acquire.plan import load_plan
    from opacityhull.imageio import read_exr, read_hdr
    from opacityhull.rigs.config import load_rig_config

    w, s, m = seeds["work"], seeds["session"], seeds["model"]
    view = sorted((m / "views").glob("*.exr"))[0].name
    bundle_bin = sorted(p.name for p in (w / "bundle").iterdir() if p.suffix == ".bin")[0]
    return {
        "session.toml": (s, Path("session.toml"), _read_session, True, False),
        "manifest.jsonl": (s, Path("manifest.jsonl"), _read_session, True, True),
        "rig TOML": (w / "rig", Path("rig.toml"), lambda d: load_rig_config(d / "rig.toml"), True, False),
        "plan TOML": (w / "plan", Path("plan.toml"), lambda d: load_plan(d / "plan.toml"), True, False),
        "COLMAP cameras.bin": (seeds["colmap"], Path("cameras.bin"), _read_colmap, False, False),
        "COLMAP images.bin": (seeds["colmap"], Path("images.bin"), _read_colmap, False, False),
        "COLMAP points3D.bin": (seeds["colmap"], Path("points3D.bin"), _read_colmap, False, False),
        "transforms.json": (
            seeds["ns"],
            Path("transforms.json"),
            lambda d: _import_ns(d / "transforms.json"),
            True,
            True,
        ),
        "EXR": (m / "views", Path(view), lambda d: read_exr(d / view), False, False),
        "HDR": (w / "hdr", Path("map.hdr"), lambda d: read_hdr(d / "map.hdr"), False, False),
        "PLY": (m, Path("surfels.ply"), lambda d: _read_model_ply(d / "surfels.ply"), False, False),
        "viewer manifest.json": (w / "bundle", Path("manifest.json"), _read_bundle, True, True),
        "viewer chunk": (w / "bundle", Path(bundle_bin), _read_bundle, False, False),
    }


def _text_colmap(seeds: dict[str, Path]) -> Path:
    """A text COLMAP model (cameras.txt, images.txt) from the binary one."""
    d = seeds["work"] / "colmap_text"
    d.mkdir(exist_ok=True)
    for name in ("cameras.txt", "images.txt", "points3D.txt"):
        shutil.copy(seeds["colmap"] / name, d / name)
    return d


# ----------------------------------------------------------------------------- run


class _Hang(Exception):
    pass


def _alarm(signum, frame):
    raise _Hang()


def classify(fn: Callable, folder: Path, timeout_s: int = 20) -> tuple[str, str]:
    """The outcome of ``fn(folder)``; more than ``timeout_s`` is a finding ("hang")."""
    import signal

    from opacityhull.errors import OpacityHullError

    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(timeout_s)
    try:
        fn(folder)
        return "ok", ""
    except _Hang:
        return "crash", f"hang: no answer within {timeout_s} s"
    except (OpacityHullError, KeyboardInterrupt) as e:
        msg = str(e)
        return (
            "named" if (folder.name in msg or str(folder) in msg) else "unnamed"
        ), f"{type(e).__name__}: {msg[:200]}"
    except (FileNotFoundError, IsADirectoryError) as e:  # the CLI maps these to a named exit 2
        return ("named" if e.filename else "unnamed"), f"{type(e).__name__}: {e}"
    except Exception as e:  # noqa: BLE001 - every other exception is a finding
        return "crash", f"{type(e).__name__}: {str(e)[:200]}"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def run(per_format: int, cli_samples: int) -> dict:
    import logging

    import resource

    import warnings

    logging.disable(logging.WARNING)  # the readers' notes are not findings
    warnings.simplefilter("ignore", RuntimeWarning)  # numpy's overflow notes on 1e308 poses
    # a reader that allocates what a mutated count says is a finding (MemoryError), not an OOM kill
    limit = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (min(4 << 30, limit[1]) if limit[1] > 0 else 4 << 30, limit[1]))
    work = Path(tempfile.mkdtemp(prefix="opacityhull-fuzz-"))
    try:
        seeds = make_seeds(work)
        fmts = formats(seeds)
        ct = _text_colmap(seeds)
        fmts["COLMAP cameras.txt"] = (ct, Path("cameras.txt"), _read_colmap, True, False)
        fmts["COLMAP images.txt"] = (ct, Path("images.txt"), _read_colmap, True, False)
        counts: dict[str, Counter] = defaultdict(Counter)
        findings: list[dict] = []
        t0 = time.perf_counter()
        for name, (folder, rel, fn, text, json_like) in fmts.items():
            original = (folder / rel).read_bytes()
            ok, why = classify(fn, folder)
            assert ok == "ok", f"{name}: the unmutated seed does not read: {why}"

            _fuzz_one(name, folder, rel, fn, text, json_like, original, per_format, work, counts, findings)
        in_process_s = time.perf_counter() - t0
        cli = _cli_sample(seeds, cli_samples, work)
    finally:
        shutil.rmtree(work, ignore_errors=True)
        logging.disable(logging.NOTSET)
        resource.setrlimit(resource.RLIMIT_AS, limit)  # the caller (a test session) gets its own back
    total = sum(c["ok"] + c["named"] + c["unnamed"] + c["crash"] for c in counts.values())
    kinds = Counter((f["format"], f["error"].split(":")[0]) for f in findings)
    return {
        "inputs": total,
        "per_format": {k: {o: v[o] for o in ("ok", "named", "unnamed", "crash")} for k, v in counts.items()},
        "findings": findings[:50],
        "finding_kinds": [{"format": f, "exception": e, "count": n} for (f, e), n in kinds.items()],
        "clean": not findings and cli["tracebacks"] == 0,
        "in_process_s": round(in_process_s, 1),
        "cli": cli,
    }


def _fuzz_one(name, folder, rel, fn, text, json_like, original, per_format, work, counts, findings) -> None:
    """``per_format`` hypothesis examples of one format (a closure: @given takes no defaults)."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    @settings(
        max_examples=per_format,
        database=None,
        deadline=None,
        derandomize=True,
        suppress_health_check=list(HealthCheck),  # pyright: ignore[reportArgumentType]
    )
    @given(st.sampled_from(KINDS), st.data())
    def one(kind, data):
        bad = mutate(original, kind, data.draw, text=text, json_like=json_like)
        copy = Path(tempfile.mkdtemp(prefix="in-", dir=work)) / folder.name
        shutil.copytree(folder, copy)
        (copy / rel).write_bytes(bad)
        outcome, detail = classify(fn, copy)
        counts[name][outcome] += 1
        if outcome in ("unnamed", "crash"):
            findings.append({"format": name, "mutation": kind, "outcome": outcome, "error": detail})
        shutil.rmtree(copy.parent, ignore_errors=True)

    one()


def _cli_sample(seeds: dict[str, Path], n: int, work: Path) -> dict:
    """``n`` mutated model views and COLMAP models through the real CLI (a subprocess each):
    the exit code is 0, 2 or 4 and no traceback reaches the user."""
    rng = np.random.default_rng(1)
    codes: Counter = Counter()
    tracebacks = 0
    for i in range(n):
        d = Path(tempfile.mkdtemp(prefix="cli-", dir=work))
        if i % 2 == 0:
            m = d / "model"
            shutil.copytree(seeds["model"], m)
            v = sorted((m / "views").glob("*.exr"))[int(rng.integers(0, 4))]
            b = bytearray(v.read_bytes())
            cut = int(rng.integers(0, len(b)))
            v.write_bytes(bytes(b[:cut]))
            argv = ["render", str(m), "--out", str(d / "o.png")]
        else:
            c = d / "sparse"
            shutil.copytree(seeds["colmap"], c)
            f = c / ["cameras.bin", "images.bin", "points3D.bin"][int(rng.integers(0, 3))]
            b = bytearray(f.read_bytes())
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
            f.write_bytes(bytes(b[: int(rng.integers(len(b) // 2, len(b) + 1))]))
            argv = ["import", "colmap", "--model", str(c), "--images", str(seeds["colmap"].parents[1] / "images")]
            argv += ["--out", str(d / "s")]
        r = subprocess.run([sys.executable, "-m", "opacityhull.cli", *argv], capture_output=True, text=True)
        codes[r.returncode] += 1
        tracebacks += "Traceback" in r.stderr or r.returncode not in (0, 2, 4)
        shutil.rmtree(d, ignore_errors=True)
    return {"inputs": n, "exit_codes": dict(codes), "tracebacks": tracebacks}


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="20 inputs per format, 4 through the CLI (make bench).")
    ap.add_argument("--per-format", type=int, default=None, help="Mutated inputs per format (default 200).")
    ap.add_argument("--json", action="store_true", help="Print the report as JSON.")
    a = ap.parse_args()
    per = a.per_format or (20 if a.quick else 200)
    rep = run(per, 4 if a.quick else 20)
    if a.json:
        print(json.dumps(rep, indent=1))
        return
    print(f"fuzz: {rep['inputs']} mutated inputs in-process ({rep['in_process_s']} s), {rep['cli']['inputs']} via CLI")
    for k, v in rep["per_format"].items():
        print(f"  {k:24s} " + "  ".join(f"{o} {n}" for o, n in v.items()))
    print(f"  CLI exit codes {rep['cli']['exit_codes']}, tracebacks {rep['cli']['tracebacks']}")
    for f in rep["finding_kinds"]:
        print(f"  FINDING {f['format']}: {f['exception']} x{f['count']}")
    for f in rep["findings"][:20]:
        print(f"    {f['format']} / {f['mutation']}: {f['outcome']}: {f['error']}")
    print("clean" if rep["clean"] else "NOT CLEAN")


if __name__ == "__main__":
    main()
