"""``magmesh warm``: compile every compiled core (numba) into its on-disk cache, or load it from there.

The services' fleet cores (ingest's rules, the DMC detectors, the heading filter, calibration) are compiled on
first use and cached beside their sources. A first compile takes seconds per core; ``./run`` calls this once
after setting up, so no service pays for it when it starts (a cached core loads in well under a second).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time

#: modules with a ``warm()`` function (those not installed are skipped)
MODULES = ("services.ingest.fleet", "services.dmc_detector.fleet", "services.heading_fuser.compiled",
           "services.heading_fuser.fleet", "services.calibration.fleet")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("warm", help="compile the compiled cores into their disk cache (./run does it)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quiet", action="store_true", help="print only failures")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    t_all = time.perf_counter()
    failed = 0
    for name in MODULES:
        try:
            mod = importlib.import_module(name)
        except ImportError:
            continue
        warm = getattr(mod, "warm", None)
        if warm is None:
            continue
        t0 = time.perf_counter()
        try:
            warm()
        except Exception as e:  # noqa: BLE001 - say which core, go on with the others
            failed += 1
            print(f"magmesh warm: {name}: {type(e).__name__}: {e}", file=sys.stderr)
            continue
        if not args.quiet:
            print(f"{name}: ready in {time.perf_counter() - t0:.2f} s")
    if not args.quiet:
        print(f"compiled cores ready in {time.perf_counter() - t_all:.1f} s")
    return 1 if failed else 0
