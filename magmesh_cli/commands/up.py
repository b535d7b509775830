"""``magmesh up [manifest]``: run the mesh."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from magmesh.paths import DEPLOY_DIR


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start every process of a mesh manifest and supervise them",
                       description="Start the mesh: host the Zenoh endpoint, start every enabled process of the "
                       "manifest, restart crashed ones with backoff, stop all on Ctrl-C.")
    p.add_argument("manifest", nargs="?", default=str(DEPLOY_DIR / "mesh.toml"), help="mesh manifest (TOML)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--endpoint", default=None, help="Zenoh endpoint to host (default: the manifest's)")
    p.add_argument("--log-dir", default=None, help="where process logs go (default .magmesh/logs/<time>)")
    p.add_argument("--only", default=None, metavar="NAMES",
                   help="comma-separated process names: start only these (enabled or not)")
    p.add_argument("--set", action="append", default=[], metavar="PROCESS.NAME=VALUE",
                   help="override one process setting (repeatable), e.g. sim-car-1.speed=0")
    p.add_argument("--secure", nargs="?", const=".magmesh/secure", default=None, metavar="DIR",
                   help="run the secured mesh: mutual TLS and access control per role; certificates and "
                   "configuration files are made in DIR if absent (default .magmesh/secure)")
    p.add_argument("--insecure", action="store_true",
                   help="allow an endpoint beyond loopback without TLS and access control (anyone who reaches "
                   "it can steer the mesh)")
    p.add_argument("--keep-going", action="store_true",
                   help="keep the other processes running when one is given up (it failed on start "
                   "[mesh] give_up_after times in a row, default 5); the exit code is still 1")
    p.add_argument("--quiet", action="store_true", help="no status line")
    p.add_argument("--log-level", default="INFO")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from magmesh.runtime import setup_logging

    from ..supervisor import ManifestError, Supervisor, check_processes, load_manifest

    setup_logging(args.log_level)
    # the whole manifest is checked before anything starts: structure, modules, implementations, settings
    m = load_manifest(args.manifest)
    names = [p.name for p in m.processes]
    if args.only is not None:
        wanted = [n.strip() for n in args.only.split(",") if n.strip()]
        missing = [n for n in wanted if n not in names]
        if missing or not wanted:
            raise ManifestError(f"--only {args.only!r}: no process named {', '.join(missing) or '(none given)'} in "
                                f"{m.path}; its processes: {', '.join(names)}.")
        for p in m.processes:
            p.enabled = p.name in wanted
    for item in args.set:
        target, sep, value = item.partition("=")
        name, dot, key = target.partition(".")
        procs = [p for p in m.processes if p.name == name]
        if not (sep and dot and key.strip()):
            raise ManifestError(f"--set {item!r}: expected PROCESS.NAME=VALUE, e.g. sim-car-1.speed=2.")
        if not procs:
            raise ManifestError(f"--set {item!r}: no process named {name!r} in {m.path}; its processes: "
                                f"{', '.join(names)}.")
        procs[0].settings[key.strip()] = value
    check_processes(m)
    sup = Supervisor(m, endpoint=args.endpoint, log_dir=Path(args.log_dir) if args.log_dir else None, quiet=args.quiet)
    sup.keep_going = args.keep_going
    from .. import secure

    problem = secure.exposure_error(sup.endpoint, m.zenoh_config, bool(args.secure), args.insecure)
    if problem:
        print(problem, file=sys.stderr)
        return 2
    if args.secure:
        try:
            prepared = secure.secure_supervisor(sup, m, Path(args.secure))
        except (ValueError, RuntimeError, OSError) as e:
            print(f"magmesh up --secure: {e}", file=sys.stderr)
            return 2
        if not args.quiet:
            print(f"secured mesh: mutual TLS and access control on {prepared['endpoint']}; operators attach with "
                  f"--config {prepared['operator']}", flush=True)
    rc = sup.run(args.duration)
    from .. import cli

    cli.EXIT_WITHOUT_FINALISING = True  # every child and the session are stopped (see cli.run_main)
    return rc
