"""A rig whose backdrops are monitors (video output, under Xvfb) with Samsung MDC control
ports (emulated): the rig TOML, `rig check` reporting each panel's model, mode and locks,
and a capture that locks the panels and refuses to start matting while one may drift."""

from __future__ import annotations

import copy
import importlib.util
import shutil

import numpy as np
import pytest

from opacityhull.errors import ConfigError, DeviceError
from opacityhull.rigs.config import parse_rig_config
from opacityhull.rigs.testing import LAB_RIG_CONFIG, LabRig, lab_video_rig_config, read_xwd, xvfb

needs_x = pytest.mark.skipif(
    shutil.which("Xvfb") is None or importlib.util.find_spec("pyglet") is None,
    reason="Xvfb or pyglet missing (apt-get install xvfb; pip install 'opacityhull[video]'; make system-deps)",
)


@pytest.fixture(scope="module")
def server():
    from opacityhull.rigs import video

    with xvfb(((64, 48), (48, 48))) as (display, fbdir):
        yield display, fbdir
        video.disconnect(display)


def test_video_rig_toml_parses():
    cfg = parse_rig_config(lab_video_rig_config(x_display=":5"), source="rig.toml")
    bd = cfg.backdrops
    assert bd is not None and bd.driver == "video" and bd.monitor_map == {"bottom": "screen@1", "back": "screen@0"}
    assert (bd.response_ms, bd.x_display) == (5.0, ":5")
    assert [(p.name, p.display_id, p.url) for p in cfg.panels] == [
        ("panels.bottom", 1, "emulator:mdc#bottom"),
        ("panels.back", 2, "emulator:mdc#back"),
    ]
    assert cfg.device_urls()["panels.back"] == "emulator:mdc#back" and "backdrops" not in cfg.device_urls()


@pytest.mark.parametrize(
    "edit, match",
    [
        (lambda c: c["devices"]["panels"]["back"].update(id=254), r"devices.panels.back.id: MDC display id.*broadcast"),
        (lambda c: c["devices"]["panels"]["back"].update(id=-3), r"devices.panels.back.id: MDC display id"),
        (lambda c: c["devices"]["backdrops"]["monitors"].pop("back"), r"no monitor for display 'back'"),
        (lambda c: c["devices"]["backdrops"]["monitors"].update(back="screen@1"), "two displays on one monitor"),
        (lambda c: c["devices"]["panels"]["back"].update(url="emulator:mdc#bottom"), "give each device its own port"),
        (lambda c: c["devices"]["panels"]["back"].update(input="vga"), "panel input 'vga'"),
        (lambda c: c["devices"]["backdrops"].update(driver="hdmi"), r"devices.backdrops.driver: expected one of"),
        (
            lambda c: c["devices"].update(backdrops=copy.deepcopy(c["devices"]["backdrops"]) | {"driver": "ohdc2"}),
            "unknown key",
        ),
    ],
)
def test_bad_video_rig_toml_is_named(edit, match):
    cfg = lab_video_rig_config()
    edit(cfg)
    with pytest.raises(ConfigError, match=match):
        parse_rig_config(cfg, source="rig.toml")


@needs_x
def test_rig_check_reports_monitors_and_each_panels_model_mode_and_locks(server):
    from opacityhull.rigs.emulators.launch import start_emulators
    from opacityhull.rigs.rig import check_rig_config

    display, _ = server
    cfg = parse_rig_config(lab_video_rig_config(x_display=display), source="rig.toml")
    with start_emulators(cfg) as emus:
        infos = {i.name: i for i in check_rig_config(emus.config, timeout_s=0.5)}
    assert infos["backdrops"].ok and "bottom on screen@1" in infos["backdrops"].detail
    for name in ("panels.bottom", "panels.back"):
        i = infos[name]
        assert i.ok and i.identity == "QM55R-EMU", i.detail
        # out of the box the emulated panel dims itself: rig check says so, by name
        assert "DRIFTS: energy saving low (auto-brightness), dynamic contrast on" in i.detail
        assert i.state["temperature_c"] == 38


@needs_x
def test_capture_locks_the_panels_and_shows_the_patterns_on_the_monitors(server, tmp_path):
    from opacityhull.acquire.runner import run_capture
    from tests.acquire.rigkit import tiny_plan

    display, fbdir = server
    with LabRig(lab_video_rig_config(x_display=display)) as rig:
        shots = []

        def grab(cam):
            pid = rig.backdrops.shown()["back"]
            if pid is not None and cam.index == 0:
                shots.append((pid, read_xwd(fbdir / "Xvfb_screen0"), rig.backdrops.current("back")))

        rig.cameras[0].before_capture = grab
        res = run_capture(rig, tiny_plan(), tmp_path / "s", rig_source="lab-video")
        assert res.complete
        assert all(not e.drifting() for e in rig.panel_emulators.values())
        assert shots
        for _, screen, image in shots:  # the pattern on the back monitor while the camera exposed
            rows = ((np.arange(48) + 0.5) * image.shape[0] / 48).astype(int)
            cols = ((np.arange(64) + 0.5) * image.shape[1] / 64).astype(int)
            np.testing.assert_array_equal(screen, image[rows][:, cols])
        assert read_xwd(fbdir / "Xvfb_screen0").max() == 0  # left blank by rig.safe()


@needs_x
def test_matting_refuses_a_panel_that_keeps_dynamic_contrast_on(server, tmp_path):
    from opacityhull.acquire.runner import run_capture
    from opacityhull.rigs.panels import DisplayDrift
    from tests.acquire.rigkit import tiny_plan

    display, _ = server
    with LabRig(lab_video_rig_config(x_display=display)) as rig:
        rig.panel_emulators["back"].locked.add("dynamic_contrast")
        with pytest.raises(
            DeviceError, match=r"panels.back.*refused SET DYNAMIC CONTRAST 0.*--allow-display-drift"
        ) as ei:
            run_capture(rig, tiny_plan(), tmp_path / "s", rig_source="lab-video")
        assert isinstance(ei.value.__cause__, DisplayDrift)
        assert not list((tmp_path / "s" / "images").rglob("*matting*"))  # calibration only
        logged = []
        res = run_capture(rig, tiny_plan(), tmp_path / "s", resume=True, allow_display_drift=True, log=logged.append)
        assert res.complete
        assert any("display back: dynamic contrast on" in m for m in logged)


def test_dry_run_prices_no_pattern_upload_for_video_backdrops():
    from opacityhull.acquire.schedule import MotionRates, estimate, schedule
    from tests.acquire.rigkit import tiny_plan

    cfg = lab_video_rig_config()
    rates = MotionRates.from_devices(cfg["devices"])
    geometry = parse_rig_config(cfg, source="rig.toml").geometry
    est = estimate(tiny_plan(), geometry, rates, schedule(tiny_plan(), geometry))
    assert not rates.display_uploads and est.uploads == 0 and est.upload_s == 0.0
    ohdc = MotionRates.from_devices(LAB_RIG_CONFIG["devices"])
    est2 = estimate(tiny_plan(), geometry, ohdc, schedule(tiny_plan(), geometry))
    assert est2.uploads > 0
