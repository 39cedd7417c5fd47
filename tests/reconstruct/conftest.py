import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))  # rcsynth (analytic test scenes)


@pytest.fixture(scope="session")
def cli_session(tmp_path_factory):
    """:func:`rcsynth.cli_session`: the small sphere session that the build-CLI tests of
    several modules run on (built once: they only read it)."""
    import rcsynth

    return rcsynth.cli_session(tmp_path_factory, "cli_session")
