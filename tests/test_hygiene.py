"""Repository hygiene that a clean machine depends on.

A clean machine has only what the project installs: every subprocess that a test or command starts must use the
project's interpreter (``sys.executable``), never whatever ``python`` happens to be on PATH.
"""
from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SKIP = {".venv", ".git", ".magmesh", "node_modules", "__pycache__"}
# argv[0] given as a bare interpreter name (python, python3, python3.11, each in quotes)
BARE = re.compile(r"""[\[(,]\s*["']python(?:3(?:\.\d+)?)?["']""")
SHELL_BARE = re.compile(r"^\s*(?:exec\s+)?python3?\s", re.M)


def _files(*suffixes: str):
    for p in REPO.rglob("*"):
        if p.suffix in suffixes and not (SKIP & set(p.relative_to(REPO).parts)) and p.is_file():
            yield p


def test_no_subprocess_uses_a_bare_python():
    found = []
    for p in _files(".py"):
        for n, line in enumerate(p.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if BARE.search(line) and "test_hygiene" not in p.name:
                found.append(f"{p.relative_to(REPO)}:{n}: {line.strip()}")
    assert not found, "use sys.executable, not a bare python:\n" + "\n".join(found)


def test_no_shell_script_runs_a_bare_python():
    found = []
    for p in _files(".sh", ""):
        if p.suffix == "" and not p.read_bytes().startswith(b"#!"):
            continue
        text = p.read_text(encoding="utf-8", errors="replace")
        for m in SHELL_BARE.finditer(text):
            found.append(f"{p.relative_to(REPO)}: {m.group(0).strip()}")
    assert not found, "scripts must run the project's interpreter:\n" + "\n".join(found)


def test_the_guard_sees_a_bare_python():
    py = "py" + "thon"  # spelled in two parts so that this file does not hold the pattern it looks for
    assert BARE.search(f'args = ["{py}", "-m", "magmesh"]')
    assert BARE.search(f"Popen(('{py}3', '-c', 'x'))")
    assert not BARE.search("args = [sys.executable, '-m', 'magmesh']")
    assert SHELL_BARE.search("exec python -m x\n")


def test_every_process_entry_sets_one_blas_thread_before_numpy_loads():
    """A service, simulator or bench process starts with one BLAS thread unless its user chose otherwise: with a
    BLAS pool per process, spinning worker threads starved a DMC mesh test 9-fold on a busy 2-core machine."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS")}
    code = "import os, {pkg}; print(os.environ.get('OPENBLAS_NUM_THREADS'), os.environ.get('OMP_NUM_THREADS'))"
    for pkg in ("magmesh", "services", "sim_publishers", "bench"):
        r = subprocess.run([sys.executable, "-c", code.format(pkg=pkg)], cwd=REPO, env=env, capture_output=True,
                           text=True, timeout=60)
        assert r.returncode == 0, (pkg, r.stderr[-500:])
        assert r.stdout.split() == ["1", "1"], (pkg, r.stdout)
    r = subprocess.run([sys.executable, "-c", code.format(pkg="services")], cwd=REPO, capture_output=True, text=True,
                       env={**env, "OPENBLAS_NUM_THREADS": "2"}, timeout=60)
    assert r.stdout.split() == ["2", "1"], "a user's own setting is kept"


def test_imports_run_one_way():
    """The runtime library (magmesh) imports neither the operator app (magmesh_cli), the services, the
    simulators nor the evaluations; services, simulators and the contract never import the app or the
    evaluations (``python -m magmesh`` is the one entry point that starts the app)."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    rules = {"magmesh": ("magmesh_cli", "services", "sim_publishers", "bench"),
             "schemas": ("magmesh", "magmesh_cli", "services", "sim_publishers", "bench"),
             "services": ("magmesh_cli", "bench", "sim_publishers"),
             "sim_publishers": ("magmesh_cli", "bench")}
    bad = []
    for pkg, banned in rules.items():
        for f in sorted((root / pkg).rglob("*.py")):
            if f.name == "__main__.py" and pkg == "magmesh":
                continue
            for node in ast.walk(ast.parse(f.read_text())):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else (
                    [node.module] if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 else [])
                for n in names:
                    if n.split(".")[0] in banned:
                        bad.append(f"{f.relative_to(root)} imports {n}")
    assert not bad, bad
