"""``magmesh report``: an HTML page with PNG plots and a summary table from a recording or a live run.

    magmesh report run.mcap -o report/                 # then open report/index.html
    magmesh report --live --duration 60 -o report/     # record the live mesh for 60 s, then report
    magmesh report drive.mcap rerun.mcap --exclude 'magmesh/*/dmc' -o cmp/   # several recordings merged

With several recordings, the messages of all are merged (``--exclude`` drops keys from every input but
the last, e.g. the old detector's output when the last file holds a re-run through a new one).

Geomagnetic fixes are drawn on the vehicle's anomaly map: ``--map`` or the ``map`` entry of the vehicle's
table in the manifest (``deploy/mesh.toml`` by default).
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
import tomllib
from collections import Counter
from pathlib import Path

from magmesh import zconf
from magmesh.paths import DEPLOY_DIR

from ..recording import load_liveliness, load_messages, matches_any, summarize
from ..report.data import plotted_keys

log = logging.getLogger("magmesh_cli.report")


def register(subparsers) -> None:
    p = subparsers.add_parser("report", help="HTML report with plots from a recording or a live run",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    p.set_defaults(func=run)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("inputs", nargs="*", metavar="RECORDING", help="MCAP recording(s) (omit with --live)")
    p.add_argument("-o", "--output", default="report", help="output directory (default report/)")
    p.add_argument("--live", action="store_true", help="record the live mesh first (see --duration, --keys)")
    p.add_argument("--duration", type=float, default=30.0, help="--live: seconds to record (default 30)")
    p.add_argument("--keys", nargs="+", default=None, metavar="KEYEXPR", help="only these keys")
    p.add_argument("--exclude", nargs="+", default=(), metavar="KEYEXPR",
                   help="with several recordings: leave these keys out of all but the last")
    p.add_argument("--vehicles", nargs="+", default=None, help="only these vehicles")
    p.add_argument("--title", default=None)
    p.add_argument("--map", default=None, help="anomaly map for geomagnetic plots (file under data/ or synthetic:N)")
    p.add_argument("--manifest", default=str(DEPLOY_DIR / "mesh.toml"),
                   help="manifest whose vehicle tables name each vehicle's map")
    p.add_argument("--no-progress", action="store_true")
    zconf.add_zenoh_args(p)


def vehicle_maps(manifest: str | None, override: str | None, vehicles) -> tuple[dict, dict]:
    """(vehicle → GridMap, vehicle → main field nT) from --map (all vehicles) or each vehicle's table in
    the manifest (``map``; ``main_field_nt`` or the IGRF field at ``lat_deg``/``lon_deg``/``alt_m``, as
    the geomagnetic matcher computes it)."""
    import numpy as np

    from magmesh.geomap import core_field_enu_nt, load_map

    tables: dict[str, dict] = {}
    if manifest and Path(manifest).exists():
        with open(manifest, "rb") as f:
            tables = {v: t for v, t in tomllib.load(f).get("vehicles", {}).items() if isinstance(t, dict)}
    cache: dict[str, object] = {}
    grids, main = {}, {}
    for v in vehicles:
        table = tables.get(v, {})
        spec = override or table.get("map")
        if not spec:
            continue
        try:
            if spec not in cache:
                cache[spec] = load_map(str(spec))
            grids[v] = cache[spec]
        except (OSError, ValueError) as e:
            log.warning("map %s for %s not loaded: %s", spec, v, e)
            continue
        if "main_field_nt" in table:
            main[v] = float(table["main_field_nt"])
        elif "lat_deg" in table and "lon_deg" in table:
            main[v] = float(np.linalg.norm(core_field_enu_nt(table["lat_deg"], table["lon_deg"],
                                                             table.get("alt_m", 0.0))))
    return grids, main


def make_report(paths, out_dir: str | Path, key_exprs=None, vehicles=None, title=None, map_spec=None,
                manifest=None, progress: bool = False, exclude=()) -> Path:
    """Report on one recording or several merged (``exclude`` drops keys from all but the last)."""
    from ..report import build_report

    paths = [Path(p) for p in ([paths] if isinstance(paths, (str, Path)) else paths)]
    bad: Counter = Counter()
    msgs: list = []
    liveliness: list = []
    notes = []
    for i, path in enumerate(paths):
        summ = summarize(path)
        wanted = plotted_keys([k for k in summ["keys"] if matches_any(key_exprs, k)], vehicles)
        got = load_messages(path, wanted, counts=bad, progress=progress) if wanted else []
        if exclude and i < len(paths) - 1:
            got = [(k, m) for k, m in got if not matches_any(exclude, k)]
        msgs += got
        liveliness += load_liveliness(path)
        notes.append(f"Recording {path.name}: {summ['messages']} samples over {summ['duration_s']:.1f} s "
                     f"(receive time) on {len(summ['keys'])} keys; {len(got)} messages used.")
    found = sorted({k.split("/")[1] for k, _ in msgs})
    path = paths[-1]
    if bad:
        notes.append(f"{sum(bad.values())} recorded payloads did not decode as magmesh messages and are not plotted.")
    grids, main_field = vehicle_maps(manifest, map_spec, found)
    return build_report(msgs, out_dir, title=title or f"magmesh run {path.stem}",
                        source=", ".join(str(p) for p in paths), liveliness=sorted(liveliness), grids=grids,
                        main_field_nt=main_field, vehicles=vehicles, progress=progress, notes=notes)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    out = Path(args.output)
    if args.live:
        from .record import format_counts, record

        out.mkdir(parents=True, exist_ok=True)
        path = out / "run.mcap"
        paths = [path]
        print(f"recording the live mesh for {args.duration:g} s to {path} …", file=sys.stderr)
        with zconf.open_client(args, 10.0, "magmesh report --live") as session:  # bounded connection
            counts = record(session, path, args.keys or (), args.duration, stop=threading.Event())
        print(format_counts(counts, path), file=sys.stderr)
    else:
        if not args.inputs:
            raise SystemExit("magmesh report: give a recording (run.mcap) or --live")
        paths = [Path(p) for p in args.inputs]
        for p in paths:
            if not p.exists():
                raise SystemExit(f"magmesh report: {p} does not exist")
    index = make_report(paths, out, args.keys, args.vehicles, args.title, args.map, args.manifest,
                        progress=not args.no_progress and sys.stderr.isatty(), exclude=args.exclude)
    print(f"report written: {index.resolve()}")
    return 0
