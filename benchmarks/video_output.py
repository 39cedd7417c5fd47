"""Video-output backdrops (issue #36): how long one pattern takes to reach the screen.

A private Xvfb server with two X screens (1920x1080 and 1280x720, the two monitors of
a video-output rig) and a :class:`~opacityhull.rigs.video.DisplayOutput` on them; each
show draws the pattern full-screen (nearest neighbour), swaps and ``glFinish``es. For
pattern sizes from the matting patterns (64x36) to a full-HD natural image, it times
``swapped - requested`` of :class:`~opacityhull.rigs.video.ShowTiming` (the panel's
response time, 0 here, comes on top on a real rig) and checks the last frame against
the screen read back from Xvfb's framebuffer. Mesa's software OpenGL (llvmpipe) on a
virtual server: a GPU on a real output is faster; the figures bound what the capture
pays per pattern on a machine without one. Under load from other processes the times
are inflated.

    .venv/bin/python benchmarks/video_output.py [--quick] [--json] [--repeats N]

Writes ``benchmarks/out/video_output.md``. Skips (exit 0, saying so) without Xvfb or pyglet.
"""

from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import numpy as np
from benchkit import out_dir, parser, print_result, report_head

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
SIZES = [(36, 64), (360, 640), (1080, 1920)]


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="10 shows per size instead of 60")
    ap.add_argument("--repeats", type=int, default=None, help="shows per pattern size")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if shutil.which("Xvfb") is None or importlib.util.find_spec("pyglet") is None:
        print("video_output: skipped — Xvfb or pyglet missing (make system-deps; pip install 'opacityhull[video]')")
        return 0
    from opacityhull.rigs import video
    from opacityhull.rigs.testing import read_xwd, xvfb

    n = args.repeats or (10 if args.quick else 60)
    rng = np.random.default_rng(0)
    rows = []
    with xvfb(((1920, 1080), (1280, 720))) as (display, fbdir):
        out = video.DisplayOutput(monitors={"back": "screen@0", "bottom": "screen@1"}, x_display=display)
        with out:
            for h, w in SIZES:
                pats = [rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for _ in range(4)]
                times = []
                for i in range(n):
                    t = out.show_image("back", pats[i % 4], pattern_id=i)
                    times.append(t.swapped - t.requested)
                screen = read_xwd(fbdir / "Xvfb_screen0")
                last = pats[(n - 1) % 4]
                r = ((np.arange(1080) + 0.5) * h / 1080).astype(int)
                c = ((np.arange(1920) + 0.5) * w / 1920).astype(int)
                exact = bool(np.array_equal(screen, last[r][:, c]))
                ms = np.array(times) * 1000
                rows.append(
                    {
                        "pattern": f"{w}x{h}",
                        "shows": n,
                        "median_ms": float(np.median(ms)),
                        "p95_ms": float(np.percentile(ms, 95)),
                        "screen_exact": exact,
                    }
                )
        video.disconnect(display)
    lines = report_head(
        "Video-output backdrops: pattern to screen",
        f"Xvfb 1920x1080 + 1280x720, Mesa llvmpipe, {n} shows per size on the 1920x1080 monitor; "
        "time from show_image() to the end of glFinish() after the swap (the panel's response time is extra).",
    )
    lines += [
        "| pattern | shows | median ms | p95 ms | screen = nearest-scaled pattern |",
        "| --- | --- | --- | --- | --- |",
    ] + [
        f"| {r['pattern']} | {r['shows']} | {r['median_ms']:.1f} | {r['p95_ms']:.1f} | {r['screen_exact']} |"
        for r in rows
    ]
    OUT.mkdir(parents=True, exist_ok=True)
    report = OUT / "video_output.md"
    report.write_text("\n".join(lines) + "\n")
    print_result({"rows": rows}, report, as_json=args.json)
    return 0 if all(r["screen_exact"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
