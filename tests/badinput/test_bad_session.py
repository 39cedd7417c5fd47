"""Bad inputs of ``session verify|info|hdr`` and of the session format itself
(``session.py``: what ``build`` and every other reader trusts)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from badkit import Case, invoke, run_case


def _set_session_key(key: str, value: str):
    def setup(root: Path):
        p = root / "session.toml"
        text = p.read_text()
        text, n = re.subn(rf"(?m)^{key} = .*$", f"{key} = {value}", text)
        if n == 0:
            text = text.replace("[session]\n", f"[session]\n{key} = {value}\n", 1)
        p.write_text(text)

    return setup


def _edit_record(index: int, **changes):
    def setup(root: Path):
        p = root / "manifest.jsonl"
        lines = p.read_text().splitlines()
        d = json.loads(lines[index])
        d.update(changes)
        lines[index] = json.dumps(d)
        p.write_text("\n".join(lines) + "\n")

    return setup


VERIFY = ("session", "verify", "{S}")
HDR = ("session", "hdr", "{S}")
WHITE_LEVEL_TEXT = r"session.toml: \[session\] white_level = \"bright\", expected a finite number > 0"
CASES = [
    Case("verify-missing-folder", ("session", "verify", "{T}/nosuch"), 2, r"nosuch: no such session folder"),
    Case("info-missing-folder", ("session", "info", "{T}/nosuch", "--json"), 2, r"nosuch: no such session folder"),
    Case(
        "verify-a-file",
        ("session", "verify", "{S}/session.toml"),
        2,
        r"session.toml is a file, expected a session folder",
    ),
    Case(
        "verify-table-deg-not-a-number",
        VERIFY,
        4,
        r"NOT OK.*invalid records 1.*manifest.jsonl:3: record .*table_deg = \"ninety\", expected a finite number",
        setup=_edit_record(2, table_deg="ninety"),
    ),
    Case(
        "verify-camera-negative", VERIFY, 4, r"camera = -1, expected an integer >= 0", setup=_edit_record(0, camera=-1)
    ),
    Case(
        "verify-phase-unknown",
        VERIFY,
        4,
        r"phase = \"nosuch\", expected one of calibration",
        setup=_edit_record(1, phase="nosuch"),
    ),
    Case("verify-white-level-text", VERIFY, 4, WHITE_LEVEL_TEXT, setup=_set_session_key("white_level", '"bright"')),
    Case(
        "info-white-level-zero",
        ("session", "info", "{S}"),
        4,
        r"session.toml: \[session\] white_level = 0, expected a finite number > 0",
        setup=_set_session_key("white_level", "0"),
    ),
    Case(
        "hdr-unknown-phase",
        (*HDR, "--phase", "nosuch"),
        2,
        r"--phase 'nosuch': not a phase; expected one of calibration",
    ),
    Case("hdr-absent-phase", (*HDR, "--phase", "envmatte"), 2, r"--phase 'envmatte': .* has no images of that phase"),
    Case(
        "hdr-white-level-text", HDR, 4, r"white_level = \"bright\"", setup=_set_session_key("white_level", '"bright"')
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_session_input(case, session_dir, tmp_path):
    run_case(case, inputs={"S": session_dir}, tmp_path=tmp_path)


def test_verify_ok_on_the_intact_session(session_dir):
    r = invoke(["session", "verify", session_dir, "--json"])
    rep = json.loads(r.stdout)
    assert r.exit_code == 0 and rep["ok"] and rep["invalid"] == []


def test_check_manifest_finds_wrong_sha_wrong_size_and_a_duplicate_id(session_dir, tmp_path):
    import shutil

    from opacityhull.errors import FormatError
    from opacityhull.session import Session, check_manifest, require_manifest_ok

    root = tmp_path / "s"
    shutil.copytree(session_dir, root)
    assert check_manifest(Session.open(root)) == []
    lines = (root / "manifest.jsonl").read_text().splitlines()
    recs = [json.loads(x) for x in lines]
    # a wrong sha (same size), and an id listed again for another file
    recs[0]["sha256"] = "0" * 64
    dup = dict(recs[2], id=recs[1]["id"])
    (root / "manifest.jsonl").write_text("\n".join(json.dumps(r) for r in [*recs, dup]) + "\n")
    problems = check_manifest(Session.open(root))
    assert any(recs[0]["id"] in p and "sha256" in p for p in problems), problems
    assert any("listed twice" in p and recs[1]["id"] in p for p in problems), problems
    with pytest.raises(FormatError, match="manifest.jsonl"):
        require_manifest_ok(Session.open(root))
    # a re-shoot (same id, same path, appended) is not a duplicate
    (root / "manifest.jsonl").write_text("\n".join(lines + [lines[3]]) + "\n")
    assert check_manifest(Session.open(root)) == []


def test_check_finite_names_nan_and_inf():
    from opacityhull.session import check_finite

    img = np.ones((4, 5, 3), np.float32)
    assert check_finite(img, where="v") is None
    img[1, 2, 0] = np.nan
    img[3, 4] = np.inf
    note = check_finite(img, where="images/x.exr")
    assert note.startswith("images/x.exr: 2 pixel(s) are not finite (1 NaN, 3 Inf values)")


def test_a_record_of_the_wrong_type_never_reaches_build(session_dir, tmp_path):
    """build reads through Session.open: the "ninety" record is corrupt data (exit 4),
    not a TypeError traceback, and nothing is written."""
    import shutil

    root = tmp_path / "S"
    shutil.copytree(session_dir, root)
    _edit_record(2, table_deg="ninety")(root)
    r = invoke(["build", root, "--out", tmp_path / "m"])
    assert r.exit_code == 4, r.output
    assert re.search(r"table_deg = \"ninety\", expected a finite number", " ".join(r.stderr.split()))
    assert not (tmp_path / "m" / "model.toml").exists()
