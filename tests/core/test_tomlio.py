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


# --------------------------------------------------------------------------- writing (#33)

import math  # noqa: E402
import tomllib  # noqa: E402

import numpy as np  # noqa: E402
from hypothesis import given, settings, strategies as st  # noqa: E402

from opacityhull.errors import InputError  # noqa: E402
from opacityhull.tomlio import join_nones, split_nones, toml_dumps  # noqa: E402

_keys = st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs", "Cc")), min_size=1, max_size=6)
_scalars = st.one_of(
    st.booleans(),
    st.integers(-(2**63), 2**63 - 1),
    st.floats(allow_nan=False),
    st.text(alphabet=st.characters(codec="utf-8", exclude_categories=("Cs",)), max_size=12),
)
_values = st.recursive(
    _scalars,
    lambda inner: st.one_of(st.lists(inner, max_size=4), st.dictionaries(_keys, inner, max_size=4)),
    max_leaves=12,
)


@settings(max_examples=150, deadline=None)
@given(data=st.dictionaries(_keys, _values, max_size=6))
def test_toml_dumps_is_tomli_w_and_reads_back(data):
    """tomli-w writes TOML (#33): what ``toml_dumps`` writes, ``tomllib`` reads back equal."""
    import tomli_w

    text = toml_dumps(data)
    assert text == tomli_w.dumps(data)
    assert tomllib.loads(text) == data


def test_toml_dumps_takes_numpy_values_leaves_out_none_and_keeps_nan():
    d = {
        "a": np.float32(0.5),
        "b": np.int64(3),
        "c": np.array([1.0, 2.0]),
        "t": {"x": None, "y": (1, 2), "z": np.bool_(True)},
        "rows": [{"id": "v0", "deg": np.float64(30.0)}, {"id": "v1", "deg": 60.0}],
        "n": float("nan"),
        "i": -math.inf,
        "p": None,
    }
    got = tomllib.loads(toml_dumps(d))
    assert got["a"] == 0.5 and got["b"] == 3 and got["c"] == [1.0, 2.0] and "p" not in got
    assert got["t"] == {"y": [1, 2], "z": True}
    assert got["rows"] == [{"id": "v0", "deg": 30.0}, {"id": "v1", "deg": 60.0}]
    assert math.isnan(got["n"]) and got["i"] == -math.inf
    with pytest.raises(InputError, match=r"None .*t\.y"):
        toml_dumps({"t": {"y": [1, None]}})


def test_split_and_join_nones_round_trip():
    d = {"a": 1, "b": None, "m": {"c": None, "d": 2.0}, "e": [1, 2]}
    table, nones = split_nones(d)
    assert table == {"a": 1, "m": {"d": 2.0}, "e": [1, 2]} and sorted(nones) == ["b", "m.c"]
    assert join_nones(table, nones) == d


def test_model_toml_stores_build_config_as_a_table_and_reads_old_json(tmp_path):
    """model.toml's build_config was a JSON string inside TOML (#33): now a table, the
    None options listed beside it; models with the JSON string still read."""
    import json
    from dataclasses import replace

    from opacityhull.model import OpacityHullModel
    from opacityhull.reconstruct.build import BuildConfig
    from opacityhull.reconstruct.matte_step import _jsonable
    from opacityhull.evaluate.holdout import build_config_of
    from opacityhull.render.synthetic import make_sphere_model
    from opacityhull.model import write_model

    cfg = replace(BuildConfig(), pca_block=None, hull_res=64, refine=True)  # None here is not the default (8)
    m = make_sphere_model(200, width=16, height=12, table_step_deg=90.0)
    want = _jsonable(cfg.to_dict())
    root = write_model(
        tmp_path / "m", views=m.views, surfels=m.surfels, view_rgba=m.view_rgba,
        provenance={"session": "s", "build_config": want},
    )  # fmt: skip
    meta = tomllib.loads((root / "model.toml").read_text())
    assert isinstance(meta["provenance"]["build_config"], dict)
    assert "pca_block" in meta["provenance"]["build_config_none"]
    model = OpacityHullModel.open(root)
    assert model.build_config == want
    got = build_config_of(model)[0]
    assert got.pca_block is None and got.hull_res == 64 and got.refine
    # an older model: the same options as a JSON string
    meta["provenance"] = {"session": "s", "build_config": json.dumps(want, sort_keys=True)}
    (root / "model.toml").write_text(toml_dumps(meta))
    old = OpacityHullModel.open(root)
    assert old.build_config == want and build_config_of(old)[0].pca_block is None
