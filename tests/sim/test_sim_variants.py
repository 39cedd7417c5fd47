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
    monkeypatch.setenv(V.ENV_VARIANT, "cuda_ad_rgb")  # forcing the GPU variant is allowed
    assert V.choose_variant() == "cuda_ad_rgb"
    assert V.variant_report()["source"].startswith("environment") and V.variant_report()["gpu"]
    monkeypatch.setenv(V.ENV_VARIANT, "cuda_rgb_typo")
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
        return False  # as if there were no GPU and libLLVM were missing

    monkeypatch.setattr(V, "probe_variant", fake_probe)
    monkeypatch.setattr(V, "_chosen", None)
    assert V.choose_variant(refresh=True) == "scalar_rgb"
    assert calls == ["cuda_ad_rgb", "llvm_ad_rgb"]
    data = json.loads((tmp_path / "opacityhull" / "mitsuba-variant.json").read_text())
    assert data["variant"] == "scalar_rgb"
    assert data["probes"] == {"cuda_ad_rgb": False, "llvm_ad_rgb": False}
    monkeypatch.setattr(V, "_chosen", None)
    assert V.choose_variant() == "scalar_rgb" and calls == ["cuda_ad_rgb", "llvm_ad_rgb"]  # from the file
    assert V.variant_report()["probes"] == {"cuda_ad_rgb": False, "llvm_ad_rgb": False}
    monkeypatch.setattr(V, "_chosen", None)


@pytest.mark.parametrize(
    "works,expected,probed",
    [
        ({"cuda_ad_rgb", "llvm_ad_rgb"}, "cuda_ad_rgb", ["cuda_ad_rgb"]),  # a GPU: CUDA, LLVM never probed
        ({"llvm_ad_rgb"}, "llvm_ad_rgb", ["cuda_ad_rgb", "llvm_ad_rgb"]),  # these machines
        (set(), "scalar_rgb", ["cuda_ad_rgb", "llvm_ad_rgb"]),  # neither JIT backend
        ({"cuda_ad_rgb"}, "cuda_ad_rgb", ["cuda_ad_rgb"]),  # GPU, broken libLLVM
    ],
)
def test_selection_prefers_cuda_then_llvm_then_scalar(works, expected, probed):
    """The selection logic with a fake probe result (no GPU here to run the variant)."""
    calls = []

    def probe(v):
        calls.append(v)
        return v in works

    variant, verdicts = V.select_variant(probe)
    assert variant == expected and calls == probed
    assert verdicts == {v: v in works for v in probed}


def test_a_gpu_found_by_the_probe_is_chosen_cached_and_reported(monkeypatch, tmp_path):
    monkeypatch.delenv(V.ENV_VARIANT, raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(V, "probe_variant", lambda v, **kw: v == "cuda_ad_rgb")
    monkeypatch.setattr(V, "_chosen", None)
    assert V.choose_variant(refresh=True) == "cuda_ad_rgb"
    rep = V.variant_report()
    assert rep["gpu"] is True and rep["probes"] == {"cuda_ad_rgb": True}
    monkeypatch.setattr(V, "_chosen", None)
    monkeypatch.setattr(V, "probe_variant", lambda *a, **k: pytest.fail("cached: must not probe"))
    assert V.choose_variant() == "cuda_ad_rgb"
    monkeypatch.setattr(V, "_chosen", None)
