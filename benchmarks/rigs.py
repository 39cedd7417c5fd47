"""Rig driver latency: command round trips and poll rates over a pty and over TCP.

Real drivers (:mod:`opacityhull.rigs.motion`, :mod:`opacityhull.rigs.lights`) talk to the
emulators through real ptys / sockets, in one process (the emulator's serving thread
shares the GIL with the driver, so these are upper bounds on overhead). Measured:

* ``echo``      the floor: a one-line ping-pong through the same server and transport;
* ``status``    ``GrblController.status()`` (``?`` -> ``<...>``): the move-polling rate;
* ``line``      ``GrblController.send_line("G90")`` -> ``ok``;
* ``move``      ``GrblAxis.move_to`` of an instant move (status, line, status);
* ``dmx_params`` Enttec label-3 request/reply;
* ``dmx_send``  512-channel universes pushed back to back (until the emulator has them).

Each is compared with what the real hardware allows: a GRBL status exchange (``?`` + a
~41-byte report at 115200 baud 8N1) takes 3.6 ms on the wire alone, and GRBL needs 5-20 ms
to generate a report; a full DMX512 universe takes 22.7 ms on the DMX line (44 Hz; the
DMX USB Pro outputs at most 40 packets/s). The ratio column says how many times faster
the software path is than that hardware limit.

    .venv/bin/python benchmarks/rigs.py [--quick] [--json]

Writes ``benchmarks/out/rigs.md`` and ``benchmarks/out/rigs.png``.
"""

from __future__ import annotations

import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from opacityhull.rigs.emulators.base import EmulatedDevice, EmulatorServer, Reply  # noqa: E402
from opacityhull.rigs.emulators.enttec import EnttecEmulator  # noqa: E402
from opacityhull.rigs.emulators.grbl import GrblEmulator  # noqa: E402
from opacityhull.rigs.lights import EnttecDmx  # noqa: E402
from opacityhull.rigs.motion import GrblAxis, GrblController  # noqa: E402
from opacityhull.rigs.transport import SerialTransport  # noqa: E402
from benchkit import out_dir, parser  # noqa: E402

OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)

BAUD = 115200
WIRE_STATUS_S = (1 + 41) * 10 / BAUD  # '?' out, '<Idle|MPos:0.000,0.000,0.000|FS:0,0>\r\n' back
WIRE_LINE_S = (4 + 4) * 10 / BAUD  # 'G90\n' out, 'ok\r\n' back
WIRE_MOVE_S = 2 * WIRE_STATUS_S + (16 + 4) * 10 / BAUD  # status, 'G90 G0 X12.500\n' + ok, status
DMX_FRAME_S = 92e-6 + 12e-6 + 513 * 44e-6  # break + MAB + start code and 512 slots at 250 kbaud


class Pong(EmulatedDevice):
    name = "pong"

    def receive(self, data):
        return [Reply(b"<>\r\n")] * data.count(b"?")


def timed(fn, n: int, warmup: int) -> np.ndarray:
    for _ in range(warmup):
        fn()
    t = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter()
        fn()
        t[i] = time.perf_counter() - t0
    return t


def row(name: str, kind: str, t: np.ndarray, limit_s: float | None, note: str) -> dict:
    med = float(np.median(t))
    return {
        "measure": name,
        "transport": kind,
        "n": int(t.size),
        "median_us": med * 1e6,
        "p95_us": float(np.percentile(t, 95)) * 1e6,
        "p99_us": float(np.percentile(t, 99)) * 1e6,
        "rate_hz": 1.0 / med,
        "hw_limit_hz": (1.0 / limit_s) if limit_s else None,
        "x_faster_than_hw": (limit_s / med) if limit_s else None,
        "note": note,
        "samples_s": t,
    }


def bench_kind(kind: str, n: int) -> list[dict]:
    rows = []
    warm = max(10, n // 20)
    with EmulatorServer(Pong(), kind=kind) as srv:
        tr = SerialTransport(srv.url, timeout_s=2.0)
        with tr:

            def ping():
                tr.write(b"?")
                tr.read_until(b"\n")

            rows.append(row("echo", kind, timed(ping, n, warm), None, "transport + server floor"))
    emu = GrblEmulator(steps_per_deg=80.0)
    with EmulatorServer(emu, kind=kind) as srv:
        ctl = GrblController.from_url(srv.url)  # 2 s per reply
        ax = GrblAxis(ctl, axis="X", steps_per_deg=80.0, max_rate_deg_s=30.0, accel_deg_s2=60.0, name="turntable")
        with ctl:
            rows.append(row("status", kind, timed(ctl.status, n, warm), WIRE_STATUS_S, "'?' -> report"))
            rows.append(row("line", kind, timed(lambda: ctl.send_line("G90"), n, warm), WIRE_LINE_S, "'G90' -> ok"))
            angles = iter(np.tile([12.5, 0.0], n + warm))
            rows.append(
                row(
                    "move",
                    kind,
                    timed(lambda: ax.move_to(next(angles)), n, warm),
                    WIRE_MOVE_S,
                    "instant move: status, line, status",
                )
            )
    emu = EnttecEmulator()
    with EmulatorServer(emu, kind=kind) as srv:
        dmx = EnttecDmx.from_url(srv.url)  # 2 s per reply
        with dmx:
            rows.append(
                row("dmx_params", kind, timed(dmx.get_widget_parameters, n, warm), None, "label 3 request/reply")
            )
            universe = bytes(range(256)) * 2
            base = emu.dmx_packets
            t0 = time.perf_counter()
            for _ in range(n):
                dmx.send_dmx(universe)
            deadline = time.monotonic() + 30
            while emu.dmx_packets < base + n and time.monotonic() < deadline:
                time.sleep(0.0005)
            dt = time.perf_counter() - t0
            if emu.dmx_packets < base + n:
                raise RuntimeError(f"emulator got {emu.dmx_packets - base} of {n} DMX packets")
            per = np.full(n, dt / n)
            r = row("dmx_send", kind, per, DMX_FRAME_S, "512-ch universes until received")
            r["MB_s"] = n * 518 / dt / 1e6
            rows.append(r)
    return rows


def main(argv=None) -> int:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="fewer samples (~5 s)")
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    args = ap.parse_args(argv)
    n = 300 if args.quick else 3000
    t0 = time.perf_counter()
    rows = bench_kind("pty", n) + bench_kind("tcp", n)
    wall = time.perf_counter() - t0

    OUT.mkdir(parents=True, exist_ok=True)
    md = [
        "# Rig driver latency (driver + emulator in one process)",
        "",
        f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"load {os.getloadavg()[0]:.1f}; n = {n} per row; run `.venv/bin/python benchmarks/rigs.py"
        f"{' --quick' if args.quick else ''}`.",
        "",
        "Hardware limits: GRBL status exchange 3.6 ms on the wire at 115200 baud (plus 5-20 ms report "
        "generation in GRBL); DMX512 universe 22.7 ms on the line (DMX USB Pro: <= 40 packets/s).",
        "",
        "| measure | transport | median µs | p95 µs | p99 µs | rate /s | hardware limit /s | × faster than hw |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        hw = f"{r['hw_limit_hz']:.0f}" if r["hw_limit_hz"] else "—"
        x = f"{r['x_faster_than_hw']:.1f}" if r["x_faster_than_hw"] else "—"
        md.append(
            f"| {r['measure']} | {r['transport']} | {r['median_us']:.0f} | {r['p95_us']:.0f} | "
            f"{r['p99_us']:.0f} | {r['rate_hz']:.0f} | {hw} | {x} |"
        )
    dmx = [r for r in rows if r["measure"] == "dmx_send"]
    md += ["", "DMX throughput: " + ", ".join(f"{r['transport']} {r['MB_s']:.1f} MB/s" for r in dmx) + ".", ""]
    (OUT / "rigs.md").write_text("\n".join(md) + "\n")

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 2, figsize=(11, 4))
        for r in rows:
            if r["measure"] == "dmx_send":
                continue
            s = np.sort(r["samples_s"]) * 1e6
            axes[0].plot(
                s,
                np.linspace(0, 1, s.size),
                ls="-" if r["transport"] == "pty" else "--",
                label=f"{r['measure']} ({r['transport']})",
            )
        axes[0].axvline(WIRE_STATUS_S * 1e6, color="k", lw=0.8)
        axes[0].text(WIRE_STATUS_S * 1e6, 0.05, " GRBL '?' wire time", fontsize=8)
        axes[0].set_xscale("log")
        axes[0].set_xlabel("round trip, µs")
        axes[0].set_ylabel("fraction of calls")
        axes[0].set_title("Latency CDF (solid: pty, dashed: TCP)")
        axes[0].legend(fontsize=7)
        lim = [r for r in rows if r["x_faster_than_hw"]]
        labels = [f"{r['measure']}\n{r['transport']}" for r in lim]
        axes[1].bar(range(len(lim)), [r["x_faster_than_hw"] for r in lim], color="tab:blue")
        axes[1].axhline(1.0, color="k", lw=0.8)
        axes[1].set_xticks(range(len(lim)), labels, fontsize=7)
        axes[1].set_yscale("log")
        axes[1].set_ylabel("software rate / hardware limit")
        axes[1].set_title("Headroom over the physical link")
        fig.tight_layout()
        fig.savefig(OUT / "rigs.png", dpi=100)
        plt.close(fig)
    except ImportError:  # pragma: no cover
        pass

    summary = {
        "benchmark": "rigs",
        "quick": args.quick,
        "n": n,
        "wall_s": wall,
        "results": [{k: v for k, v in r.items() if k != "samples_s"} for r in rows],
        "outputs": [str(OUT / "rigs.md"), str(OUT / "rigs.png")],
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print("\n".join(md[6:]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
