"""tomlio: one TOML reader naming the file, typed getters naming the key."""

from __future__ import annotations

import pytest

from opacityhull.errors import ConfigError, FormatError
from opacityhull.tomlio import TomlContext, read_toml


def test_read_toml_parses(tmp_path):
    p = tmp_path / "a.toml"
    p.write_text('x = 1\n[t]\ny = "z"\n')
    assert read_toml(p) == {"x": 1, "t": {"y": "z"}}


@pytest.mark.parametrize(
    "content,match",
    [
        (b"x = = 1\n", "invalid TOML"),
        (b'x = "\xff\xfe"\n', "not a text file"),
    ],
)
def test_read_toml_bad_content_names_file(tmp_path, content, match):
    p = tmp_path / "bad.toml"
    p.write_bytes(content)
    with pytest.raises(FormatError, match=match) as e:
        read_toml(p)
    assert str(p) in str(e.value)
    with pytest.raises(ConfigError, match=match):
        read_toml(p, error=ConfigError)


def test_read_toml_missing_and_folder(tmp_path):
    with pytest.raises(ConfigError, match=r"no such rig TOML") as e:
        read_toml(tmp_path / "nope.toml", error=ConfigError, what="rig TOML")
    assert "nope.toml" in str(e.value)
    with pytest.raises(FormatError, match="is a folder"):
        read_toml(tmp_path)


def test_context_getters_name_source_and_key():
    c = TomlContext("rig.toml", error=ConfigError)
    d = {"a": 1, "b": 2.5, "s": "x", "f": True, "bad": "one", "inf": float("inf"), "t": {}}
    assert c.num("dev", d, "a") == 1.0 and c.num("dev", d, "zz", 3) == 3.0
    assert c.int_("dev", d, "a", None, 0, 5) == 1
    assert c.str_("dev", d, "s") == "x" and c.bool_("dev", d, "f") is True
    assert c.table("dev.t", d["t"]) == {}
    cases = [
        (lambda: c.num("dev", d, "bad"), "rig.toml: dev.bad: expected a number, got 'one'"),
        (lambda: c.num("dev", d, "inf"), "dev.inf: expected a number"),
        (lambda: c.num("dev", d, "f"), "dev.f: expected a number, got True"),  # bool is not a number
        (lambda: c.num("dev", d, "a", positive=True) and c.num("dev", {"a": 0}, "a", positive=True), "must be > 0"),
        (lambda: c.num("dev", d, "missing"), "rig.toml: dev: missing key 'missing'"),
        (lambda: c.int_("dev", d, "b", None, 0, 5), "dev.b: expected an integer in 0..5, got 2.5"),
        (lambda: c.int_("dev", d, "a", None, 2, 5), "expected an integer in 2..5, got 1"),
        (lambda: c.str_("dev", d, "a"), "dev.a: expected a string, got 1"),
        (lambda: c.bool_("dev", d, "a"), "dev.a: expected true or false, got 1"),
        (lambda: c.table("dev.s", d["s"]), "dev.s: expected a table, got str"),
        (lambda: c.keys("dev", d, {"a"}), "unknown key"),
    ]
    for f, msg in cases:
        with pytest.raises(ConfigError) as e:
            f()
        assert msg in str(e.value)


def test_callers_use_it(tmp_path):
    """model.toml, session.toml, rig and plan TOMLs that are not text all read the same way."""
    from opacityhull.acquire.plan import load_plan
    from opacityhull.model import OpacityHullModel
    from opacityhull.rigs.config import load_rig_config
    from opacityhull.session import Session

    bad = b"\xff\xfe = 1\n"
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "model.toml").write_bytes(bad)
    (tmp_path / "s").mkdir()
    (tmp_path / "s" / "session.toml").write_bytes(bad)
    (tmp_path / "rig.toml").write_bytes(bad)
    (tmp_path / "plan.toml").write_bytes(bad)
    with pytest.raises(FormatError, match="model.toml: not a text file"):
        OpacityHullModel.open(tmp_path / "m")
    with pytest.raises(FormatError, match="session.toml: not a text file"):
        Session.open_meta(tmp_path / "s")
    with pytest.raises(ConfigError, match="rig.toml: not a text file"):
        load_rig_config(tmp_path / "rig.toml")
    with pytest.raises(ConfigError, match="plan.toml: not a text file"):
        load_plan(tmp_path / "plan.toml")
