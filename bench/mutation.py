"""Mutation testing of the pure cores: ``python -m bench.mutation [CORE ...]``.

Each core is mutated by ``mutmut`` (plausible one-line bugs: a flipped comparison, ``min`` for ``max``, a
changed constant, a dropped argument, ...) and every mutant is run against **that core's own test files
only**, so the score says how firmly those tests hold the method, not whether some far-away end-to-end
test happens to notice. A mutant is *killed* when a test fails (or it hangs past mutmut's timeout); it
*survives* when they all pass; *no tests* means no selected test even runs the mutated function. The score
is killed / (killed + survived + no tests): code no test reaches counts against the core.

Not mutated (``do_not_mutate_patterns``): the text of error messages and log lines — a reworded message is
not a wrong result. Everything else in the file is.

The run works in a scratch copy of the repository (``--workdir``, default a new temporary directory) with
its own ``pyproject.toml`` ``[tool.mutmut]`` section per core, so the tree itself is never touched. It is
slow (minutes per core on 2 cores) and is not part of the test suite. ``--survivors`` prints the diff of
every surviving mutant. Exit status 0 when every core reached ``--goal`` (default 90 %), 1 when not,
2 on a usage error.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class Core:
    source: str
    tests: tuple[str, ...]
    #: tests of those files left out of the mutation run (too slow to run once per mutant; each is named
    #: with the reason in CORES, and the pins that replace it are in ``tests``)
    deselect: tuple[str, ...] = ()


#: each pure core and its own test files
CORES: dict[str, Core] = {
    "dmc_core": Core("services/dmc_detector/core.py", ("tests/test_dmc_core.py", "tests/test_dmc_stage1_pins.py")),
    "dmc_fcm": Core("services/dmc_detector/fcm.py", ("tests/test_dmc_fcm.py", "tests/test_dmc_fcm_pins.py")),
    "arls": Core("services/calibration/arls.py",
                 ("tests/test_calibration_core.py", "tests/test_calibration_arls_pins.py")),
    "two_step": Core("services/calibration/two_step.py",
                     ("tests/test_calibration_core.py", "tests/test_calibration_arls_pins.py",
                      "tests/test_calibration_two_step_pins.py")),
    "online_ekf": Core("services/calibration/online_ekf.py",
                       ("tests/test_calibration_core.py", "tests/test_calibration_online_ekf_pins.py")),
    # the simulated drives (30-400 s of sensor data through the whole filter, 0.5-5 s each) and the online-lag runs
    # (40 s at 285 Hz; a 70 s BROAD trial) are left out: they exercise every step at once but pin none. The step pin
    # files check each step against a reference on short inputs: prediction, accelerometer, alignment, settings and
    # reset (test_heading_step_pins.py); the field checks, window, gate, tilt leak, heading and field-direction
    # updates, modes, holds, slew, weak fusion, hard iron and re-base (test_heading_mag_pins.py); rest, noise
    # learning, zero rate, the gravity low-pass and the lag estimators (test_heading_rest_lag_step_pins.py). Two
    # rest pins (60 s of rest, two 30 s runs) are covered by the exact rest steps; the service's DMC switch is the
    # service's, not this core's (the filter's own is pinned in test_heading_pins.py).
    "heading_core": Core("services/heading_fuser/core.py",
                         ("tests/test_heading_core.py", "tests/test_heading_pins.py", "tests/test_heading_rest_pins.py",
                          "tests/test_heading_lag.py", "tests/test_heading_step_pins.py",
                          "tests/test_heading_mag_pins.py", "tests/test_heading_rest_lag_step_pins.py"),
                         deselect=tuple(f"tests/test_heading_core.py::test_{n}" for n in (
                             "aligns_and_tracks_a_turn_with_declination", "gyro_bias_is_estimated",
                             "dmc_invalid_switches_to_gyro_and_back_without_a_jump",
                             "holds_after_a_short_dmc_only_outage_scale_with_it",
                             "recovery_slews_a_drifted_heading_back_at_a_bounded_rate",
                             "field_check_rejects_a_magnet_without_dmc",
                             "long_gyro_only_stretch_raises_the_uncertainty_flag",
                             "hard_iron_tracking_keeps_the_heading_with_a_magnet_attached",
                             "agreement_from_clear_needs_the_heading_to_agree_while_the_gyro_holds_it"))
                         + ("tests/test_heading_pins.py::"
                            "test_service_gyro_only_comes_from_the_dmc_verdict_on_a_clean_field",
                            "tests/test_heading_rest_pins.py::test_rest_learns_the_sensor_noise",
                            "tests/test_heading_rest_pins.py::test_zero_rate_at_rest_learns_the_vertical_gyro_bias",
                            "tests/test_heading_lag.py::test_the_fuser_estimates_a_known_lag_online_within_3_ms",
                            "tests/test_heading_lag.py::test_a_real_trial_shifted_by_20_ms_is_estimated_20_ms_later")),
    # the slow end-to-end cases (the unordered-set pipeline against the exhaustive search, the simulated survey,
    # 20 s and more each) are left out; test_geomag_pins.py pins the same steps on small maps. The spline-cache
    # test is of magmesh/geomap.py, not of this core.
    "geomag_core": Core("services/geomag_matcher/core.py", ("tests/test_geomag_core.py", "tests/test_geomag_pins.py"),
                        deselect=("tests/test_geomag_core.py::test_pipeline_finds_the_exhaustive_answer[centre-None]",
                                  "tests/test_geomag_core.py::test_pipeline_finds_the_exhaustive_answer[corners-None]",
                                  "tests/test_geomag_core.py::test_streaming_matcher_corrects_the_simulated_ins",
                                  "tests/test_geomag_core.py::"
                                  "test_spline_cache_belongs_to_its_map_after_other_maps_are_freed")),
    # the reduced evaluation (30 s and more a run) exercises the whole monitor but pins none of its steps;
    # test_track_pins.py pins them one by one
    "track_core": Core("services/track_monitor/core.py", ("tests/test_track_core.py", "tests/test_track_pins.py"),
                       deselect=("tests/test_track_core.py::test_reduced_evaluation_meets_the_goals",)),
}

#: lines whose mutation would only change a message's wording
DO_NOT_MUTATE_PATTERNS = (
    r"^\s*raise \w+(Error|Exception)\(",
    r"\blog\.(debug|info|warning|error|exception)\(",
    r"^\s*(f?\"|f?')[^\"']*(\"|')\s*$",  # continuation lines of a message
)

STATUS_KEYS = ("killed", "timeout", "survived", "no tests", "suspicious", "skipped", "not checked", "segfault",
               "caught by type check")


def _copy_tree(dst: Path) -> None:
    """Tracked files of the repository (plus the working-tree versions), data linked rather than copied."""
    try:
        files = subprocess.run(["git", "ls-files", "-co", "--exclude-standard"], cwd=REPO, check=True,
                               capture_output=True, text=True).stdout.splitlines()
    except (OSError, subprocess.CalledProcessError):
        files = [str(p.relative_to(REPO)) for p in REPO.rglob("*") if p.is_file()
                 and not any(part in (".git", ".venv", "mutants") for part in p.relative_to(REPO).parts)]
    for rel in files:
        if rel.startswith(("data/", ".venv/", "mutants/")):
            continue
        src = REPO / rel
        if not src.is_file():
            continue
        out = dst / rel
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(src, out)
    if (REPO / "data").exists():
        (dst / "data").symlink_to(REPO / "data")


def _toml_list(items) -> str:
    return "[" + ", ".join(json.dumps(x) for x in items) + "]"


def _write_config(work: Path, core: Core) -> None:
    py = work / "pyproject.toml"
    text = py.read_text()
    text = re.sub(r"(?ms)^\[tool\.mutmut\].*?(?=^\[|\Z)", "", text)
    top = core.source.split("/")[0]
    pytest_args = ["-p", "no:randomly", "-q", "-x", "-m", "not slow"]
    for test in core.deselect:
        pytest_args += ["--deselect", test]
    text += (
        "\n[tool.mutmut]\n"
        f"source_paths = {_toml_list([top])}\n"
        f"only_mutate = {_toml_list([core.source])}\n"
        f"pytest_add_cli_args_test_selection = {_toml_list(core.tests)}\n"
        f"pytest_add_cli_args = {_toml_list(pytest_args)}\n"
        f"do_not_mutate_patterns = {_toml_list(DO_NOT_MUTATE_PATTERNS)}\n"
    )
    py.write_text(text)


def _mutmut(work: Path, *args: str, timeout_s: float | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONUNBUFFERED="1", OPENBLAS_NUM_THREADS="1", MAGMESH_STATE_DIR=str(work / "state"))
    return subprocess.run([sys.executable, "-m", "mutmut", *args], cwd=work, env=env, capture_output=True,
                          text=True, timeout=timeout_s)


def _resume(work: Path, core: Core, max_children: int, log=print) -> list[str]:
    """Bring an earlier run's test files (and the core, if it changed) up to date; return the mutants to test
    (again): those that survived, had no test, or were not reached (a run stopped before its end).

    Killed mutants stay killed: tests were only added. A core changed since the run is copied in and run once:
    mutmut mutates it again, keeps the verdicts of the functions whose source is unchanged and tests every
    mutant of the changed ones (and those not yet reached).
    """
    for rel in core.tests:
        for dst in (work / rel, work / "mutants" / rel):
            dst.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, dst)
    if (REPO / core.source).read_bytes() != (work / core.source).read_bytes():
        shutil.copy2(REPO / core.source, work / core.source)
        log(f"  {core.source} changed since the run: its changed functions' mutants are tested again", flush=True)
        _mutmut(work, "run", "--max-children", str(max_children))
    res = _mutmut(work, "results", "--all", "true")
    return [line.strip().rpartition(": ")[0] for line in res.stdout.splitlines()
            if line.strip().rpartition(": ")[2] in ("survived", "no tests", "not checked")]


def run_core(name: str, work_root: Path, max_children: int, survivors: bool, log=print, resume: bool = False,
             ) -> dict:
    core = CORES[name]
    work = work_root / name
    t0 = time.monotonic()
    if resume and (work / "mutants").is_dir():
        again = _resume(work, core, max_children, log)
        log(f"  resuming {work}: {len(again)} mutants (survived, without a test or not reached) tested again",
            flush=True)
        run = _mutmut(work, "run", "--max-children", str(max_children), *again) if again else None
    else:
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
        _copy_tree(work)
        _write_config(work, core)
        run = _mutmut(work, "run", "--max-children", str(max_children))
    res = _mutmut(work, "results", "--all", "true")
    counts = dict.fromkeys(STATUS_KEYS, 0)
    names: dict[str, list[str]] = {}
    for line in res.stdout.splitlines():
        if ":" not in line:
            continue
        mutant, _, status = line.strip().rpartition(": ")
        if status in counts:
            counts[status] += 1
            names.setdefault(status, []).append(mutant)
    total = sum(counts.values())
    if total == 0:
        tail = (run.stdout + run.stderr)[-3000:] if run is not None else ""
        code = run.returncode if run is not None else None
        raise RuntimeError(f"mutmut found no mutants for {core.source} (exit {code}):\n{tail}")
    if counts["not checked"] == total:  # mutmut stopped before the first mutant (its clean or forced-fail run)
        tail = (run.stdout + run.stderr)[-3000:] if run is not None else ""
        code = run.returncode if run is not None else None
        raise RuntimeError(f"mutmut tested none of the {total} mutants of {core.source} (exit {code}; its clean "
                           f"run of the tests or the forced-fail check stopped it; --resume with the same "
                           f"--workdir tries again):\n{tail}")
    detected = counts["killed"] + counts["timeout"] + counts["caught by type check"] + counts["segfault"]
    scored = detected + counts["survived"] + counts["no tests"]
    out = {"core": name, "source": core.source, "tests": list(core.tests),
           "deselected": list(core.deselect), "mutants": total,
           "killed": detected, "survived": counts["survived"], "no_tests": counts["no tests"],
           "other": total - scored, "score_pct": round(100.0 * detected / scored, 1) if scored else None,
           "duration_s": round(time.monotonic() - t0, 1), "survivor_names": names.get("survived", []),
           "no_test_names": names.get("no tests", [])}
    if survivors:
        for m in names.get("survived", []) + names.get("no tests", []):
            log(_mutmut(work, "show", m).stdout)
    return out


def _table(rows: list[dict]) -> str:
    lines = ["| core | file | mutants | killed | survived | no tests | score |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['core']} | {r['source']} | {r['mutants']} | {r['killed']} | {r['survived']} | "
                     f"{r['no_tests']} | {r['score_pct']} % |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.mutation", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="cores: " + ", ".join(f"{k} ({v.source})" for k, v in CORES.items()))
    ap.add_argument("cores", nargs="*", metavar="CORE", help="cores to mutate (default: all)")
    ap.add_argument("--max-children", type=int, default=os.cpu_count() or 2, help="parallel mutant runs")
    ap.add_argument("--workdir", type=Path, help="scratch directory (default: a new temporary one, removed after)")
    ap.add_argument("--goal", type=float, default=90.0, help="score each core must reach, %% (default 90)")
    ap.add_argument("--survivors", action="store_true", help="print the diff of each surviving mutant")
    ap.add_argument("--json", type=Path, help="also write the results as JSON here")
    ap.add_argument("--resume", action="store_true",
                    help="with --workdir: keep an earlier run's verdicts there and test only its survivors, "
                         "mutants without a test and those not reached, against the current test files (a changed "
                         "core: the mutants of its changed functions again); the seconds reported are those of this "
                         "pass")
    a = ap.parse_args(argv)
    unknown = [c for c in a.cores if c not in CORES]
    if unknown:
        print(f"unknown core(s) {', '.join(unknown)}; choose from {', '.join(CORES)}.", file=sys.stderr)
        return 2
    if a.resume and a.workdir is None:
        print("--resume needs --workdir: the directory of the run to resume.", file=sys.stderr)
        return 2
    try:
        import mutmut  # noqa: F401
    except ImportError:
        print("mutmut is not installed: pip install -e '.[dev]' installs it.", file=sys.stderr)
        return 2
    names = a.cores or list(CORES)
    tmp = None
    if a.workdir is None:
        tmp = tempfile.mkdtemp(prefix="magmesh-mutation-")
        work_root = Path(tmp)
    else:
        work_root = a.workdir
        work_root.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for n in names:
            print(f"mutating {CORES[n].source} against {', '.join(CORES[n].tests)} ...", flush=True)
            try:
                r = run_core(n, work_root, a.max_children, a.survivors, resume=a.resume)
            except RuntimeError as e:
                print(f"{n}: {e}", file=sys.stderr)
                return 2
            rows.append(r)
            print(f"  {n}: {r['killed']} of {r['killed'] + r['survived'] + r['no_tests']} killed "
                  f"({r['score_pct']} %), {r['survived']} survived, {r['no_tests']} without a test, "
                  f"{r['duration_s']:.0f} s", flush=True)
    finally:
        if tmp is not None:
            shutil.rmtree(tmp, ignore_errors=True)
    print()
    print(_table(rows))
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))
    below = [r["core"] for r in rows if r["score_pct"] is None or r["score_pct"] < a.goal]
    if below:
        print(f"\nbelow the {a.goal:g} % goal: {', '.join(below)}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
