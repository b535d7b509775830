"""State files (calibration sets, the track monitor's σ and routes, the alarm store, the seq journal's index) are
replaced atomically through one helper, magmesh.paths.write_atomic."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from magmesh import paths

REPO = Path(__file__).resolve().parents[1]


def test_write_atomic_replaces_the_file_and_leaves_no_temporary(tmp_path):
    p = tmp_path / "car-1__1.json"
    paths.write_atomic(p, "first")
    paths.write_atomic(p, "second")
    assert p.read_text() == "second" and sorted(x.name for x in tmp_path.iterdir()) == ["car-1__1.json"]


def test_a_write_that_fails_leaves_the_old_file_whole(tmp_path, monkeypatch):
    p = tmp_path / "s.json"
    paths.write_atomic(p, "old")
    real = Path.write_text

    def half_then_fail(self, text, *a, **k):
        real(self, text[: len(text) // 2], *a, **k)
        raise OSError("disk full")

    monkeypatch.setattr(Path, "write_text", half_then_fail)
    with pytest.raises(OSError):
        paths.write_atomic(p, "a new text")
    assert p.read_text() == "old"


def test_every_state_file_goes_through_the_helper():
    """No other code renames a temporary file over a state file by hand."""
    found = []
    for f in [*(REPO / "magmesh").rglob("*.py"), *(REPO / "services").rglob("*.py"),
              *(REPO / "magmesh_cli").rglob("*.py")]:
        for n, line in enumerate(f.read_text().splitlines(), 1):
            if re.search(r"\bos\.(replace|rename)\(", line) and f.name != "paths.py":
                found.append(f"{f.relative_to(REPO)}:{n}: {line.strip()}")
    assert not found, found
    users = {f.relative_to(REPO).as_posix() for f in [*(REPO / "magmesh").rglob("*.py"),
                                                        *(REPO / "services").rglob("*.py")]
             if "write_atomic(" in f.read_text()}
    assert {"magmesh/alarmstore.py", "magmesh/journal.py", "services/calibration/service.py",
            "services/track_monitor/service.py"} <= users, users
