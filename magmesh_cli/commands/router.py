"""``magmesh router``: a Zenoh router (a Python session in router mode) for multi-host meshes.

Each host of a multi-host mesh runs one: vehicles' publishers, services and operators connect to the router
of their own host, and the routers connect to each other (``--connect`` the other hosts' routers; links are
two-way, so one side connecting is enough). With ``--config deploy/secure/router.json5`` the router speaks
mutual TLS and enforces the mesh's access-control rules. See ``deploy/README.md``.
"""

from __future__ import annotations

import argparse
import logging
import signal
import threading
import time

from magmesh import zconf
from schemas import keys

log = logging.getLogger("magmesh.router")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("router", help="run a Zenoh router (one per host of a multi-host mesh)",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    zconf.add_zenoh_args(p)
    p.add_argument("--name", default=None, help="router name for its liveliness token (default: router-<pid>)")
    p.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--log-level", default="INFO")
    p.set_defaults(func=run)


def build_router_config(args: argparse.Namespace):
    """Router-mode configuration from the standard flags; listens on the default endpoint when nothing says
    where (never on every interface by accident)."""
    listen = args.listen
    if not listen and not args.config:
        listen = [zconf.default_endpoint()]
    return zconf.build_config("router", args.connect, listen, args.config, args.cfg, args.multicast_scouting)


def run(args: argparse.Namespace) -> int:
    import os

    import zenoh

    from magmesh.runtime import setup_logging

    setup_logging(args.log_level)
    conf = build_router_config(args)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    name = args.name or f"router-{os.getpid()}"
    with zenoh.open(conf) as session:
        token = session.liveliness().declare_token(keys.svc_token("router", name))
        log.info("router %s (zid %s) listening on %s, connecting to %s", name, session.info.zid(),
                 ", ".join(args.listen or []) or f"the endpoints of {args.config}",
                 ", ".join(args.connect or []) or (f"the endpoints of {args.config}" if args.config else "-"))
        deadline = time.monotonic() + args.duration if args.duration else None
        seen: set[str] = set()
        while not stop.wait(1.0):
            routers = {str(z) for z in session.info.routers_zid()}
            if routers != seen:
                log.info("linked routers: %s", ", ".join(sorted(routers)) or "none")
                seen = routers
            if deadline is not None and time.monotonic() >= deadline:
                break
        token.undeclare()
    log.info("router %s stopped", name)
    return 0
