"""``magmesh up [manifest]``: run the mesh."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..paths import DEPLOY_DIR


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("up", help="start every process of a mesh manifest and supervise them",
                       description="Start the mesh: host the Zenoh endpoint, start every enabled process of the "
                       "manifest, restart crashed ones with backoff, stop all on Ctrl-C.")
    p.add_argument("manifest", nargs="?", default=str(DEPLOY_DIR / "mesh.toml"), help="mesh manifest (TOML)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--endpoint", default=None, help="Zenoh endpoint to host (default: the manifest's)")
    p.add_argument("--log-dir", default=None, help="where process logs go (default .magmesh/logs/<time>)")
    p.add_argument("--quiet", action="store_true", help="no status line")
    p.add_argument("--log-level", default="INFO")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..runtime import setup_logging
    from ..supervisor import Supervisor, load_manifest

    setup_logging(args.log_level)
    m = load_manifest(args.manifest)
    sup = Supervisor(m, endpoint=args.endpoint, log_dir=Path(args.log_dir) if args.log_dir else None, quiet=args.quiet)
    return sup.run(args.duration)
