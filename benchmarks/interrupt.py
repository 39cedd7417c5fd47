"""Ctrl-C of a simulated capture: does the child always exit, and how fast?

Starts ``opacityhull capture --rig sim:builtin:diffuse?scale=0.4 --plan builtin:tiny``
(the command of tests/e2e/test_capture_resume.py) again and again, each time sending
SIGINT at a different moment, optionally with CPU hogs (``yes > /dev/null``) running to
mimic a loaded machine, and records for each try the exit code, the time from the signal
to the exit, the images listed, and whether Mitsuba's own SIGINT handler ran ("Received
interrupt signal" on stderr) or the signal was held back during a render and delivered
after it (opacityhull.interrupts' debug line). Two ways of choosing the moment:

* ``delay``: a delay after the session's manifest appears, stepped by ``--step-ms``
  (modulo ``--span-s``), so the signal lands anywhere in the run;
* ``render``: right after the child's camera starts its k-th render (k stepped 1, 4,
  7, …), so it lands while a render is running or about to.

A child still running ``--timeout`` s after its signal is a hang: its threads' stacks
(SIGUSR1, the CLI's faulthandler) go into the report, then it is killed.

``--mode stress`` hammers the mechanism itself: one process renders with the simulated
camera in a loop while SIGINTs arrive a few milliseconds apart; each must come out as an
exception the loop survives, and the loop must never stall.

    .venv/bin/python benchmarks/interrupt.py [--quick] [--tries N] [--hogs 3] [--mode both|stress]
        [--tree PATH]   # run another source tree (e.g. a checkout before the fix)

Writes ``benchmarks/out/interrupt.md`` and ``interrupt.json`` (``interrupt_stress.*``
for the stress mode).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from benchkit import out_dir, parser, report_head

ROOT = Path(__file__).resolve().parents[1]
OUT = out_dir()  # benchmarks/out, or benchmarks/out/quick with --quick (benchkit)
RIG = "sim:builtin:diffuse?scale=0.4"
PLAN = "builtin:tiny"

# the real CLI, with the deferral's logger at DEBUG on stderr, and one line
# "bench: render" each time the simulated camera starts rendering (a wrapper, so that a
# tree from before the deferral is traced the same way): what the `render` mode waits for
_CHILD = (
    "import logging, sys\n"
    "h = logging.StreamHandler(sys.stderr)\n"
    "h.setFormatter(logging.Formatter('%(name)s: %(message)s'))\n"
    "lg = logging.getLogger('opacityhull.interrupts'); lg.setLevel(logging.DEBUG); lg.addHandler(h)\n"
    "from opacityhull.sim.render import SimRenderer\n"
    "_render = SimRenderer.render\n"
    "def render(self, *a, **k):\n"
    "    sys.stderr.write('bench: render\\n')\n"
    "    return _render(self, *a, **k)\n"
    "SimRenderer.render = render\n"
    "sys.argv[0] = 'opacityhull'\n"
    "from opacityhull.cli import main\n"
    "main()\n"
)


def _default_sigint() -> None:
    # a shell running this in the background hands SIGINT down ignored
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _one(tree: Path, work: Path, *, mode: str, k: int, delay_s: float, timeout_s: float) -> dict:
    out = work / "session"
    shutil.rmtree(out, ignore_errors=True)
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(tree), NUMBA_NUM_THREADS="1")
    cmd = [sys.executable, "-c", _CHILD, "capture", "--rig", RIG, "--plan", PLAN, "--out", str(out), "--json"]
    stdout_path = work / "stdout.txt"
    with open(stdout_path, "w") as so:
        p = subprocess.Popen(
            cmd, stdout=so, stderr=subprocess.PIPE, text=True, env=env, preexec_fn=_default_sigint, cwd=work
        )
    lines: list[str] = []
    renders = [0]
    reached = threading.Event()
    assert p.stderr is not None
    stderr = p.stderr

    def read() -> None:
        for line in stderr:
            lines.append(line)
            if line.startswith("bench: render"):
                renders[0] += 1
                if renders[0] >= k:
                    reached.set()
        reached.set()  # EOF: the child ended

    t = threading.Thread(target=read, daemon=True)
    t.start()
    if mode == "render":
        reached.wait(300)
    else:
        t_end = time.monotonic() + 300
        while not (out / "manifest.jsonl").is_file() and p.poll() is None and time.monotonic() < t_end:
            time.sleep(0.005)
        time.sleep(delay_s)
    rec: dict = {"mode": mode, "k": k if mode == "render" else None, "delay_s": delay_s if mode == "delay" else None}
    if p.poll() is not None or (mode == "render" and renders[0] < k):  # ended before the signal
        t.join(10)
        rec.update(rc=p.returncode, signalled=False, latency_s=None, hang=False)
        return rec
    n_before = renders[0]
    t_sig = time.monotonic()
    p.send_signal(signal.SIGINT)
    hang = False
    try:
        p.wait(timeout_s)
    except subprocess.TimeoutExpired:
        hang = True
        native = _native_stacks(p.pid)
        p.send_signal(signal.SIGUSR1)
        time.sleep(3)
        p.kill()
        p.wait()
    latency = time.monotonic() - t_sig
    t.join(10)
    text = "".join(lines)
    try:
        summary = json.loads(stdout_path.read_text())
    except ValueError:
        summary = None
    listed = (
        sum(1 for x in (out / "manifest.jsonl").read_text().splitlines() if x.strip())
        if (out / "manifest.jsonl").is_file()
        else 0
    )
    rec.update(
        rc=p.returncode,
        signalled=True,
        latency_s=round(latency, 3),
        hang=hang,
        renders_at_signal=n_before,
        listed=listed,
        json_ok=isinstance(summary, dict) and summary.get("complete") is False,
        mitsuba_handler="Received interrupt signal" in text,
        deferred="arrived during it, delivered now" in text,
    )
    if hang:
        rec["stacks"] = text[-8000:] + "\n" + native[-12000:]
    return rec


# in-process stress: renders of the simulated camera in a loop; every SIGINT must come
# out as an exception (KeyboardInterrupt, or the RuntimeError Dr.Jit wraps it in) and
# the loop must go on; a progress line every 5 renders on stdout
_STRESS_CHILD = (
    "import faulthandler, json, signal, sys\n"
    "faulthandler.register(signal.SIGUSR1, all_threads=True)\n"
    "from opacityhull.sim.render import SimState\n"
    "from opacityhull.sim.simrig import open_sim_rig\n"
    "rig = open_sim_rig(sys.argv[1])\n"
    "cam = rig.true_cameras[0]\n"
    "c = dict(renders=0, ok=0, interrupt=0, wrapped=0, other=0)\n"
    "def caused(e):\n"
    "    while e is not None:\n"
    "        if isinstance(e, KeyboardInterrupt): return True\n"
    "        e = e.__cause__ or e.__context__\n"
    "    return False\n"
    "while True:\n"
    "    try:\n"
    "        c['renders'] += 1\n"
    "        try:\n"
    "            rig.renderer.render(cam, SimState(light_levels={0: 255}), seed=c['renders'], use_cache=False)\n"
    "            c['ok'] += 1\n"
    "        except KeyboardInterrupt:\n"
    "            c['interrupt'] += 1\n"
    "        except Exception as e:\n"
    "            c['wrapped' if caused(e) else 'other'] += 1\n"
    "        if c['renders'] % 5 == 0:\n"
    "            print(json.dumps(c), flush=True)\n"
    "    except KeyboardInterrupt:\n"
    "        c['interrupt'] += 1\n"
)


def _read_progress(stream, last: dict, t_last: list[float]) -> None:
    """The stress child's progress lines into ``last``, their time into ``t_last[0]``
    (Mitsuba's own log lines share the stream: "Received interrupt signal" in colour)."""
    for line in stream:
        if "Received interrupt signal" in line:
            last["mitsuba_handler"] = last.get("mitsuba_handler", 0) + 1
        i = line.find("{")
        try:
            last.update(json.loads(line[i:]) if i >= 0 else {})
        except ValueError:
            continue
        t_last[0] = time.monotonic()


def _stress(tree: Path, *, signals: int, max_gap_ms: float, stall_s: float, seed: int = 1) -> dict:
    """Send ``signals`` SIGINTs, ``U(0, max_gap_ms)`` apart, to a child rendering in a loop;
    a child that reports no progress for ``stall_s`` is a hang (stacks, then killed and
    restarted), one that dies is restarted."""
    import random

    rng = random.Random(seed)
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(tree), NUMBA_NUM_THREADS="1")
    tot = {"signals": 0, "renders": 0, "ok": 0, "interrupt": 0, "wrapped": 0, "other": 0, "died": 0, "hangs": 0}
    tot["mitsuba_handler"] = 0
    hang_stacks: list[str] = []
    died: list[str] = []
    while tot["signals"] < signals:
        p = subprocess.Popen(
            [sys.executable, "-c", _STRESS_CHILD, RIG],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
            preexec_fn=_default_sigint,
            cwd=tempfile.gettempdir(),  # not this checkout: `-c` puts the cwd first on sys.path
        )
        assert p.stdout is not None and p.stderr is not None
        last: dict = {}
        t_last = [time.monotonic()]
        errs: list[str] = []
        threads = [
            threading.Thread(target=_read_progress, args=(p.stdout, last, t_last), daemon=True),
            threading.Thread(target=errs.extend, args=(p.stderr,), daemon=True),
        ]
        for t in threads:
            t.start()
        while not last and p.poll() is None:  # started rendering
            time.sleep(0.05)
        t_last[0] = time.monotonic()
        while tot["signals"] < signals and p.poll() is None:
            if time.monotonic() - t_last[0] > stall_s:
                tot["hangs"] += 1
                native = _native_stacks(p.pid)
                p.send_signal(signal.SIGUSR1)
                time.sleep(3)
                p.kill()
                hang_stacks.append("".join(errs)[-8000:] + "\n" + native[-12000:])
                break
            time.sleep(rng.uniform(0, max_gap_ms) / 1000.0)
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                tot["signals"] += 1
        if p.poll() is None:
            time.sleep(0.5)  # let the last signal land, then stop
            p.kill()
        p.wait()
        for t in threads:
            t.join(5)
        if p.returncode != -signal.SIGKILL:
            tot["died"] += 1  # ended on its own: the exit code and stderr tail go into the report
            died.append(f"exit {p.returncode}: " + "".join(errs)[-600:])
        for k in ("renders", "ok", "interrupt", "wrapped", "other", "mitsuba_handler"):
            tot[k] += int(last.get(k, 0))
    return {"summary": tot, "stacks": hang_stacks, "died": died}


def _native_stacks(pid: int) -> str:
    """Every thread's native stack of a stuck process (gdb, when installed), where
    faulthandler's Python stacks end in a C call."""
    gdb = shutil.which("gdb")
    if gdb is None:
        return ""
    try:
        r = subprocess.run(
            [gdb, "-p", str(pid), "-batch", "-ex", "thread apply all bt 30"],
            capture_output=True,
            text=True,
            timeout=120,
        )
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"(gdb failed: {e})"
    return "\n".join(x for x in r.stdout.splitlines() if x.startswith(("#", "Thread")))


def _hogs(n: int) -> list[subprocess.Popen]:
    return [subprocess.Popen(["yes"], stdout=subprocess.DEVNULL) for _ in range(n)]


def main() -> None:
    ap = parser(__doc__)
    ap.add_argument("--quick", action="store_true", help="3 tries per mode")
    ap.add_argument("--tries", type=int, default=30, help="tries per mode")
    ap.add_argument(
        "--hogs", type=int, default=None, help="`yes > /dev/null` processes running meanwhile (3; --quick: 0)"
    )
    ap.add_argument("--mode", choices=("delay", "render", "both", "stress"), default="both")
    ap.add_argument("--signals", type=int, default=1500, help="SIGINTs of the `stress` mode")
    ap.add_argument("--max-gap-ms", type=float, default=40.0, help="`stress`: signals U(0, this) apart")
    ap.add_argument("--stall-s", type=float, default=30.0, help="`stress`: no progress this long = a hang")
    ap.add_argument("--step-ms", type=float, default=113.0, help="delay step of the `delay` mode")
    ap.add_argument("--span-s", type=float, default=4.0, help="delays wrap around after this")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds after the signal that count as a hang")
    ap.add_argument("--tree", type=Path, default=ROOT, help="source tree to run (PYTHONPATH)")
    ap.add_argument("--json", action="store_true", help="print the records as JSON")
    a = ap.parse_args()
    tries = 3 if a.quick else a.tries
    if a.hogs is None:
        a.hogs = 0 if a.quick else 3  # `make bench` runs every benchmark --quick: no hogs there
    if a.mode == "stress":
        _main_stress(a)
        return
    modes = ("delay", "render") if a.mode == "both" else (a.mode,)
    hogs = _hogs(a.hogs)
    recs: list[dict] = []
    try:
        with tempfile.TemporaryDirectory(prefix="oh-interrupt-") as tmp:
            for i in range(tries):
                for mode in modes:
                    r = _one(
                        a.tree.resolve(),
                        Path(tmp),
                        mode=mode,
                        k=1 + 3 * i,
                        delay_s=(i * a.step_ms / 1000.0) % a.span_s,
                        timeout_s=a.timeout,
                    )
                    recs.append(r)
                    print(json.dumps({k: v for k, v in r.items() if k != "stacks"}), file=sys.stderr, flush=True)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    sig = [r for r in recs if r["signalled"]]
    lat = sorted(r["latency_s"] for r in sig if not r["hang"])
    rcs: dict[str, int] = {}
    for r in sig:
        rcs[str(r["rc"])] = rcs.get(str(r["rc"]), 0) + 1
    summary = {
        "tree": str(a.tree.resolve()),
        "hogs": a.hogs,
        "tries": len(recs),
        "signalled": len(sig),
        "hangs": sum(r["hang"] for r in sig),
        "exit_codes": rcs,
        "max_latency_s": max(lat) if lat else None,
        "median_latency_s": lat[len(lat) // 2] if lat else None,
        "mitsuba_handler_ran": sum(r["mitsuba_handler"] for r in sig),
        "deferred_during_render": sum(r["deferred"] for r in sig),
        "bad_json": sum(not r["json_ok"] for r in sig if not r["hang"]),
    }
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "interrupt.json").write_text(json.dumps({"summary": summary, "tries": recs}, indent=1) + "\n")
    md = report_head(
        "Ctrl-C of a simulated capture (benchmarks/interrupt.py)",
        f"`capture --rig {RIG} --plan {PLAN}`, SIGINT at a different moment each try, "
        f"{a.hogs} CPU hog(s) running; modes {', '.join(modes)}; a hang = still running {a.timeout:.0f} s after "
        "the signal. Timings depend on the machine's load.",
    )
    md += ["| figure | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in summary.items()] + [""]
    for r in sig:
        if r["hang"]:
            md += [f"## hang ({r['mode']}, k={r['k']}, delay={r['delay_s']})", "", "```", r["stacks"], "```", ""]
    (OUT / "interrupt.md").write_text("\n".join(md))
    print(json.dumps(summary) if a.json else "\n".join(md))


def _main_stress(a) -> None:
    signals = 100 if a.quick else a.signals
    hogs = _hogs(a.hogs)
    try:
        res = _stress(a.tree.resolve(), signals=signals, max_gap_ms=a.max_gap_ms, stall_s=a.stall_s)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    summary = {"tree": str(a.tree.resolve()), "hogs": a.hogs, "max_gap_ms": a.max_gap_ms, **res["summary"]}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "interrupt_stress.json").write_text(json.dumps({"summary": summary, **res}, indent=1) + "\n")
    md = report_head(
        "Ctrl-C during renders, in process (benchmarks/interrupt.py --mode stress)",
        f"The simulated camera ({RIG}, camera 0, one lamp) renders in a loop; SIGINTs arrive U(0, "
        f"{a.max_gap_ms:g} ms) apart, {a.hogs} CPU hog(s) running. `interrupt`: a KeyboardInterrupt; `wrapped`: "
        "the RuntimeError Dr.Jit makes of one raised inside mi.render; `other`: any other error; "
        "`mitsuba_handler`: times Mitsuba's own SIGINT handler logged; `died`: children that ended on their own "
        "(so far a KeyboardInterrupt on the loop's own line, outside its try: exit -2); a hang = no "
        f"progress for {a.stall_s:g} s (stacks below).",
    )
    md += ["| figure | value |", "|---|---|"] + [f"| {k} | {v} |" for k, v in summary.items()] + [""]
    for st in res["stacks"]:
        md += ["## hang", "", "```", st, "```", ""]
    for d in res["died"]:
        md += ["## child ended", "", "```", d, "```", ""]
    (OUT / "interrupt_stress.md").write_text("\n".join(md))
    print(json.dumps(summary) if a.json else "\n".join(md))


if __name__ == "__main__":
    main()
