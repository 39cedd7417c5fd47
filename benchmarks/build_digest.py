"""What ``build --resume``'s verification costs: :func:`file_digest` over a model's
product files (views/, reflectance/, surfels.ply), as MB/s and seconds per model.

    python benchmarks/build_digest.py [MODEL] [--quick] [--json]

Without MODEL it hashes 48 files the size of 640x480 half RGBA views (2.46 MB each,
random bytes: the time depends only on the bytes).

Files up to ``FULL_DIGEST_MAX_BYTES`` are hashed whole (sha256); the figure says how far
that is from the cheap size + mtime + first/last MiB digest of larger files.
"""

from __future__ import annotations

import time
from pathlib import Path

from benchkit import parser

from opacityhull.reconstruct.buildstore import FULL_DIGEST_MAX_BYTES, file_digest


def measure(model: Path, repeats: int = 3) -> dict:
    files = [p for d in ("views", "reflectance") for p in sorted((model / d).glob("*")) if p.is_file()]
    files += [model / "surfels.ply"]
    nbytes = sum(p.stat().st_size for p in files)
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        for p in files:
            file_digest(p)
        best = min(best, time.perf_counter() - t)
    return {
        "model": str(model),
        "files": len(files),
        "mb": nbytes / 1e6,
        "seconds": best,
        "mb_per_s": nbytes / 1e6 / best if best > 0 else float("inf"),
        "full_digest_max_mb": FULL_DIGEST_MAX_BYTES / 1e6,  # 268 MB = 256 MiB
    }


def _stand_in(root: Path, n: int = 48) -> Path:
    import numpy as np

    rng = np.random.default_rng(0)
    (root / "views").mkdir(parents=True)
    for i in range(n):
        (root / "views" / f"v{i:03d}.exr").write_bytes(rng.bytes(640 * 480 * 4 * 2))
    (root / "surfels.ply").write_bytes(rng.bytes(300_000 * 30))
    return root


def main() -> None:
    import json
    import tempfile

    p = parser(__doc__)
    p.add_argument("model", type=Path, nargs="?")
    p.add_argument("--quick", action="store_true", help="(the same run: it takes a second)")
    p.add_argument("--json", action="store_true")
    a = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        r = measure(a.model if a.model is not None else _stand_in(Path(tmp)))
    if a.json:
        print(json.dumps(r))
    else:
        print(
            f"{r['files']} files, {r['mb']:.1f} MB: {r['seconds'] * 1e3:.0f} ms ({r['mb_per_s']:.0f} MB/s, sha256 whole "
            f"files up to {r['full_digest_max_mb']:.0f} MB)"
        )


if __name__ == "__main__":
    main()
