"""Mitsuba variant choice: probe in a subprocess, cache, environment override."""

from __future__ import annotations

import json

import pytest

from opacityhull.errors import ConfigError
from opacityhull.sim import variants as V


def test_choice_is_a_supported_variant():
    assert V.choose_variant() in V.SUPPORTED_VARIANTS


def test_environment_overrides_without_probing(monkeypatch):
    monkeypatch.setenv(V.ENV_VARIANT, "scalar_rgb")
    monkeypatch.setattr(V, "probe_variant", lambda *a, **k: pytest.fail("must not probe"))
    assert V.choose_variant() == "scalar_rgb"
    monkeypatch.setenv(V.ENV_VARIANT, "cuda_ad_rgb")
    with pytest.raises(ConfigError, match="OPACITYHULL_MITSUBA_VARIANT"):
        V.choose_variant()


def test_a_variant_that_cannot_run_fails_its_probe_without_harming_us():
    # no GPU here: the child process fails; this interpreter carries on
    assert V.probe_variant("cuda_ad_rgb", timeout_s=60) is False
    assert V.probe_variant("no_such_variant", timeout_s=60) is False


def test_probe_result_is_cached_on_disk(monkeypatch, tmp_path):
    monkeypatch.delenv(V.ENV_VARIANT, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    calls = []

    def fake_probe(variant, **kw):
        calls.append(variant)
        return False  # as if libLLVM were missing

    monkeypatch.setattr(V, "probe_variant", fake_probe)
    monkeypatch.setattr(V, "_chosen", None)
    assert V.choose_variant(refresh=True) == "scalar_rgb"
    assert calls == ["llvm_ad_rgb"]
    data = json.loads((tmp_path / "opacityhull" / "mitsuba-variant.json").read_text())
    assert data["variant"] == "scalar_rgb"
    monkeypatch.setattr(V, "_chosen", None)
    assert V.choose_variant() == "scalar_rgb" and calls == ["llvm_ad_rgb"]  # from the file, no new probe
    monkeypatch.setattr(V, "_chosen", None)
