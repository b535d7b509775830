import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import os
import tempfile

import pytest

# a fallback for code that runs at import time (collection); every test gets its own directory below
os.environ.setdefault("MAGMESH_STATE_DIR", tempfile.mkdtemp(prefix="magmesh-test-state-"))


@pytest.fixture(autouse=True)
def _own_state_dir(tmp_path_factory, monkeypatch):
    """Each test gets its own MAGMESH_STATE_DIR (persisted calibration, alarm states, swap records, ...).

    It is set in os.environ, so every process the test starts (services, the supervisor and its children)
    inherits it: no state is carried from one test, or from another run beside this one, to the next.
    """
    d = tmp_path_factory.mktemp("state")
    monkeypatch.setenv("MAGMESH_STATE_DIR", str(d))
    return d


@pytest.fixture(autouse=True)
def _heading_kernels(request):
    """A heading test starts once the background compile that pytest_sessionstart began has finished (a cold
    cache): the service then takes its compiled path, as it does on a warm cache, whatever the test order."""
    if request.module.__name__.rsplit(".", 1)[-1].startswith("test_heading"):
        from services.heading_fuser import compiled

        if compiled._WARMING is not None:
            compiled._WARMING.wait(timeout=900)


def pytest_sessionstart(session):
    """A cold numba cache: compile the heading fuser's kernels in a background process while the tests run
    (python -m services.heading_fuser.compiled --warm; tests/test_heading_compiled.py waits for it)."""
    try:
        from services.heading_fuser import compiled

        if not compiled.kernels_ready():
            compiled.warm_in_background()
    except Exception:  # noqa: BLE001 — never stop a test session for a warm-up
        pass
