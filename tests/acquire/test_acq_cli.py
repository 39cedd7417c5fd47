"""CLI: capture --dry-run (never opening the rig), session verify/info/hdr, import colmap."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from opacityhull.cli import app

from rigkit import LabRig, tiny_plan

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE_RIG = ROOT / "examples" / "rig-emulated.toml"


@pytest.fixture(scope="module")
def runner():
    return CliRunner()


def _json(res):
    return json.loads(res.stdout.strip().splitlines()[-1])


def _unopenable_rig(tmp_path) -> Path:
    """The example paper rig with every device on a port that does not exist."""
    text = EXAMPLE_RIG.read_text()
    # one port per device: the rig check (and now --dry-run) rejects devices sharing a port
    text = re.sub(r'url = "emulator:([a-z]+)"', r'url = "/dev/ttyNOPE-opacityhull-\1"', text)
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def test_dry_run_paper_never_opens_the_rig(runner, tmp_path):
    if not EXAMPLE_RIG.is_file():
        pytest.skip("examples/rig-emulated.toml not present")
    rig = _unopenable_rig(tmp_path)
    res = runner.invoke(app, ["capture", "--rig", str(rig), "--plan", "builtin:paper", "--dry-run", "--json"])
    assert res.exit_code == 0, res.output
    d = _json(res)
    views = 6 * 72
    pp = d["planned_per_phase"]
    assert pp["reflectance"] == views * 4 * 15 * 4 and pp["lightfield"] == views
    assert pp["matting"] == views * 13 and pp["calibration"] == 6 * 8
    est = d["estimate"]
    assert est["images"] == sum(pp.values()) > 100_000
    assert est["bytes"] >= est["images"] * 640 * 480 * 12
    # the time includes at least every exposure and the per-image overhead
    assert est["seconds"] > est["breakdown_s"]["exposure"] + est["breakdown_s"]["overhead"]
    assert d["complete"] is False and d["images"] == 0
    assert not (tmp_path / "out").exists()
    # human output: a table with the totals
    res = runner.invoke(app, ["capture", "--rig", str(rig), "--plan", "builtin:paper", "--dry-run"])
    assert res.exit_code == 0
    assert "reflectance" in res.output and "total" in res.output


def test_capture_argument_errors(runner, tmp_path):
    res = runner.invoke(
        app, ["capture", "--rig", str(tmp_path / "none.toml"), "--plan", "builtin:tiny", "--out", str(tmp_path / "o")]
    )
    assert res.exit_code == 2 and "none.toml" in res.output
    bad = tmp_path / "plan.toml"
    bad.write_text("[plan]\nname='x'\n[phases.teleport]\n")
    res = runner.invoke(app, ["capture", "--rig", "sim:builtin:diffuse", "--plan", str(bad), "--dry-run"])
    assert res.exit_code == 2 and "phases.teleport" in res.output


@pytest.fixture(scope="module")
def lab_session(tmp_path_factory):
    from opacityhull.acquire.runner import run_capture

    out = tmp_path_factory.mktemp("cli") / "s"
    with LabRig() as rig:
        run_capture(rig, tiny_plan(), out)
    return out


def test_session_verify_info_hdr(runner, lab_session, tmp_path):
    import shutil

    out = tmp_path / "s"
    shutil.copytree(lab_session, out)
    res = runner.invoke(app, ["session", "verify", str(out), "--json"])
    assert res.exit_code == 0, res.output
    d = _json(res)
    assert set(d) >= {"ok", "images", "missing", "corrupt", "unlisted", "per_phase"}
    assert d["ok"] and d["images"] == 222 and d["per_phase"]["reflectance"] == 96
    res = runner.invoke(app, ["session", "info", str(out), "--json"])
    assert res.exit_code == 0
    info = _json(res)
    assert info["images"] == 222 and info["phases"]["lightfield"]["views"] == 12
    assert info["phases"]["reflectance"]["exposures_s"] == [0.25, 1.0]
    # HDR merge of the reflectance brackets
    res = runner.invoke(app, ["session", "hdr", str(out), "--json"])
    assert res.exit_code == 0, res.output
    h = _json(res)
    assert h["shots"] == 48 and h["merged"] == 48
    # corrupt one image and add a stray one: verify fails with exit 4 and says which
    rec = next(p for p in (out / "images" / "lightfield").rglob("*.exr"))
    rec.write_bytes(rec.read_bytes()[:100])
    (out / "images" / "stray.exr").write_bytes(b"x")
    res = runner.invoke(app, ["session", "verify", str(out), "--json"])
    assert res.exit_code == 4
    d = _json(res)
    assert not d["ok"] and d["corrupt"] == [rec.relative_to(out).as_posix()] and d["unlisted"] == ["images/stray.exr"]


def test_import_colmap_cli(runner, tmp_path):
    from test_acq_import import _synthetic_set

    _synthetic_set(tmp_path, n=3, rgba_every=1)
    model, images, out = (str(tmp_path / name) for name in ("model", "images", "s"))
    res = runner.invoke(app, ["import", "colmap", "--model", model, "--images", images, "--out", out, "--json"])
    assert res.exit_code == 0, res.output
    assert _json(res)["images"] == 3
    res = runner.invoke(app, ["session", "verify", str(tmp_path / "s"), "--json"])
    assert res.exit_code == 0 and _json(res)["ok"]
