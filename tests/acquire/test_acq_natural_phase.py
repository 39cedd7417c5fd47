"""Issue #12 leftovers on the natural phase: ``--phase natural`` finds the images the
runner records as ``envmatte``, and the dry-run price counts the pattern uploads."""

from __future__ import annotations

import numpy as np
import pytest

from opacityhull.acquire.hdr import hdr_session
from opacityhull.errors import InputError
from opacityhull.session import PHASES, Session, SessionWriter, phase_names, shot_key

TIMES = [0.01, 0.04]


def test_phase_names_maps_natural_and_envmatte_both_ways():
    assert phase_names(["natural"]) == {"natural", "envmatte"}
    assert phase_names(["envmatte"]) == {"natural", "envmatte"}
    assert phase_names(["matting", "reflectance"]) == {"matting", "reflectance"}
    assert phase_names([]) == set()
    assert {"natural", "envmatte"} <= set(PHASES)


def _session(tmp_path):
    """Two bracketed envmatte shots (what the runner writes for [phases.natural]) and one
    reflectance shot, of known radiance."""
    h, w = 6, 8
    geo = {"target_m": [0, 0, 0], "cameras": [{"name": "c", "width": w, "height": h, "distance_m": 1.0}]}
    meta = {
        "rig": geo,
        "session": {"white_level": 1.0},
        "camera_info": [{"index": 0, "name": "c", "white_level": 1.0, "linear": True}],
    }
    root = tmp_path / "s"
    L = np.full((h, w, 3), 3.0, np.float32)
    with SessionWriter(root).create(meta) as wr:
        shots = [
            ("envmatte", dict(pattern=3)),
            ("envmatte", dict(pattern=4)),
            ("reflectance", dict(lights_deg=0.0, light=0)),
        ]
        for phase, kw in shots:
            shot = shot_key(phase, 0, 0.0, **kw)
            for k, t in enumerate(TIMES):
                wr.add_image(
                    np.clip(t * L, 0, 1).astype(np.float32),
                    id=f"{shot}/e{k}",
                    shot=shot,
                    phase=phase,
                    camera=0,
                    table_deg=0.0,
                    rel_path=f"images/{shot}_e{k}.exr",
                    exposure_s=t,
                    **kw,
                )
    return root, L


@pytest.mark.parametrize("asked", ["natural", "envmatte"])
def test_hdr_phase_natural_selects_runner_envmatte_images(tmp_path, asked):
    root, L = _session(tmp_path)
    rep = hdr_session(root, phases=[asked])
    assert rep["merged"] == 2 and rep["shots"] == 2  # the two envmatte shots, not the reflectance one
    s = Session.open(root)
    hdr = s.select(kind="hdr")
    assert {r.phase for r in hdr} == {"envmatte"}
    np.testing.assert_allclose(s.load_radiance(hdr[0].shot), L, rtol=1e-5)


def test_hdr_phase_absent_still_named(tmp_path):
    root, _ = _session(tmp_path)
    with pytest.raises(InputError, match=r"--phase 'lightfield'.*no images of that phase.*envmatte"):
        hdr_session(root, phases=["lightfield"])


# --------------------------------------------------------------------------- dry-run price of pattern uploads


def _count_link_bytes(transport):
    """Wrap a transport instance so that it counts the bytes it writes and reads."""
    n = {"tx": 0, "rx": 0}
    write, read = transport._write_raw, transport._read_raw

    def w(data):
        n["tx"] += len(data)
        return write(data)

    def r():
        data = read()
        n["rx"] += len(data)
        return data

    transport._write_raw, transport._read_raw = w, r
    return n


def test_upload_wire_bytes_equals_what_the_driver_sends_to_the_emulator():
    import rigkit

    from opacityhull.acquire.schedule import MotionRates, upload_wire_bytes
    from opacityhull.rigs.backdrops import DisplayController

    img = np.random.default_rng(4).integers(0, 256, size=(36, 64, 3), dtype=np.uint8)
    with rigkit.LabRig() as rig:
        bd = rig.backdrops
        assert isinstance(bd, DisplayController)  # the real driver, over a pty to the emulator
        n = _count_link_bytes(bd.transport)
        assert bd.upload("back", 17, img) is True
        chunk = bd.chunk_bytes
    esc = float(np.isin(img, (0x7D, 0x7E)).mean())  # image bytes the framing doubles
    want = upload_wire_bytes(64, 36, chunk_bytes=chunk, escape_rate=esc)
    # exact up to the odd escaped CRC/offset byte
    assert abs(n["tx"] + n["rx"] - want) <= 8, (n, want)
    # the figure: ~0.6 s per 64x36 pattern at 115200 baud (8N1)
    assert 0.6 < upload_wire_bytes(64, 36) / MotionRates().serial_bytes_s < 0.7


def _plan(n, steps, displays):
    from opacityhull.acquire.plan import parse_plan

    return parse_plan(
        {
            "plan": {"name": "lru", "seed": 3, "cameras": [0]},
            "table": {"steps": steps},
            "exposures": {"default_s": [0.5]},
            "phases": {"natural": {"images": n, "kernels": 4, "sources": ["noise"], "displays": displays}},
        },
        where="lru",
    )


def test_estimate_counts_the_lru_reuploads_the_runner_makes(tmp_path):
    import rigkit

    from opacityhull.acquire.runner import run_capture
    from opacityhull.acquire.schedule import MotionRates, estimate, upload_wire_bytes
    from opacityhull.rigs.backdrops import DisplayController

    # 2 domains x 34 images + 2 blacks = 70 distinct images per table angle > 64 slots
    plan = _plan(34, 2, ["back", "bottom"])
    with rigkit.LabRig() as rig:
        assert isinstance(rig.backdrops, DisplayController)
        rates = MotionRates(display_slots=rig.display_emulator.slots, display_chunk_bytes=rig.backdrops.chunk_bytes)
        est = estimate(plan, rig.geometry, rates)
        res = run_capture(rig, plan, tmp_path / "s", rig_source="lab", log=lambda m: None)
        history = [name for name, _ in rig.display_emulator.history]
        res_px = {tuple(d.resolution) for d in rig.geometry.displays}
    assert res.complete
    assert est.uploads == history.count("UPLOAD_END")
    assert est.uploads > 70  # the second table angle re-uploads: the sweep does not fit
    assert est.upload_s == pytest.approx(est.upload_bytes / rates.serial_bytes_s)
    per = max(upload_wire_bytes(*r, chunk_bytes=rates.display_chunk_bytes) for r in res_px)
    assert est.upload_bytes <= est.uploads * per + history.count("DELETE") * 16
    # a store that holds a whole table angle uploads each distinct image once
    big = estimate(plan, rig.geometry, MotionRates(display_slots=1000))
    assert big.uploads == 70 and big.upload_s < est.upload_s
    d = est.to_dict()
    assert d["pattern_uploads"]["count"] == est.uploads and d["breakdown_s"]["pattern_upload"] == est.upload_s


def test_upload_price_follows_the_rig_link_settings():
    from opacityhull.acquire.schedule import MotionRates, upload_wire_bytes

    r = MotionRates.from_devices({"backdrops": {"baudrate": 57600, "chunk_bytes": 256}})
    assert r.serial_bytes_s == 5760.0 and r.display_chunk_bytes == 256 and r.display_slots == 64
    # smaller chunks: more frames, each with its header, CRC, flags and acknowledgement
    small, big = upload_wire_bytes(64, 36, chunk_bytes=256), upload_wire_bytes(64, 36, chunk_bytes=512)
    # 27 vs 14 chunks: 13 more UPLOAD_DATA frames (flag seq cmd, id+offset, CRC-16, flag) and
    # their ACKs (flag seq ACK cmd, offset, CRC-16, flag)
    assert small - big == 13 * ((3 + 6 + 2 + 1) + (4 + 4 + 2 + 1))


def test_dry_run_reads_the_store_size_from_the_rig_config():
    """`[devices.backdrops] slots` is accepted by the rig config and is what the dry run
    prices re-uploads with (the runner asks the controller itself)."""
    from opacityhull.acquire.schedule import MotionRates

    assert MotionRates.from_devices({"backdrops": {"slots": 16}}).display_slots == 16
    assert MotionRates.from_devices({"backdrops": {}}).display_slots == 64
