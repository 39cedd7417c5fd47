"""The K of the natural-illumination estimate comes from the plan the session was
captured with (``[phases.natural] kernels``) unless the build sets ``natural_kernels``."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from opacityhull.errors import ConfigError, FormatError
from opacityhull.reconstruct.buildconfig import BuildConfig
from opacityhull.reconstruct.steps.natural import plan_kernels


def _session(phases: dict) -> SimpleNamespace:
    # what plan_kernels reads of a Session: its root (for messages) and its plan table
    return SimpleNamespace(root=Path("/data/S"), plan={"plan": {"name": "p"}, "phases": phases})


def test_the_plans_kernels_are_fitted():
    assert plan_kernels(_session({"natural": {"images": 200, "kernels": 50}}), None) == 50
    # the runner's older phase name
    assert plan_kernels(_session({"envmatte": {"images": 40, "kernels": 30}}), None) == 30


def test_default_is_the_papers_25_and_the_build_setting_wins():
    assert plan_kernels(_session({"natural": {"images": 30}}), None) == 25
    assert plan_kernels(_session({}), None) == 25
    assert plan_kernels(_session({"natural": {"images": 200, "kernels": 50}}), 12) == 12
    assert BuildConfig().natural_kernels is None


@pytest.mark.parametrize("bad", [0, 256, "25", 2.5, True])
def test_a_bad_kernels_value_names_the_file_and_key(bad):
    with pytest.raises(
        FormatError, match=r"/data/S/session\.toml: \[plan\.phases\.natural\] kernels = .*expected an integer"
    ):
        plan_kernels(_session({"natural": {"kernels": bad}}), None)


@pytest.mark.parametrize("bad", [0, 256, 2.5])
def test_a_bad_build_setting_is_refused(bad):
    with pytest.raises(ConfigError, match="natural_kernels must be None or an integer in"):
        BuildConfig(natural_kernels=bad)
