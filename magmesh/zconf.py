"""Zenoh configuration from the same flags as Zenoh's own tools.

``--mode``, ``--connect``, ``--listen``, ``--config``, ``--cfg KEY:VALUE``, ``--no-multicast-scouting``.
Without flags a magmesh process is a client of the demo mesh's router at ``tcp/127.0.0.1:7447``
(or ``$MAGMESH_ENDPOINT``), retrying until it is up; multicast scouting is off so nothing leaves
loopback unless asked.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"

#: Zenoh's link lease (ms) for magmesh's own sessions and routers. Each side of a link closes it when the other
#: sent nothing for the *other's* lease, so a process starved of CPU for longer than its peer's lease cuts the
#: link, and whatever was put meanwhile is lost (nothing buffers it). 1 s did exactly that on a loaded 2-core
#: machine: a router stalled by back-pressure sent no keep-alive for 1 s, both car simulators cut their links and
#: 3,393 samples of a car vanished (seen: seq gaps, and a lost tail nothing counted). A killed process closes its
#: TCP connections at once, so a crash is still seen at once; 10 s (Zenoh's default) bounds only a frozen process
#: or a silently lost host. Routers linking hosts (``deploy/multihost``) keep 1 s on purpose: there a link outage
#: must become a membership change in about a second.
LEASE_MS = 10_000
KEEP_ALIVE = 4  # keep-alives per lease
#: back-pressure, not loss: Zenoh closes a link whose blocking publisher waited 5 s (its default); give an
#: overloaded consumer 30 s to catch up (any loss after that shows as seq gaps in status)
WAIT_BEFORE_CLOSE_US = 30_000_000


_LOG_STARTED = False


def os_thread_name(name: str) -> None:
    """Name the calling thread for the OS (``top -H``, ``/proc/PID/task/*/comm``; 15 bytes), so a process's CPU
    shows per thread: its main loop, its reader threads, the group's rounds (Zenoh's own are rx-/tx-/net-/app-).
    Linux only; anywhere else, or if the call fails, nothing happens."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        ctypes.CDLL(None).prctl(15, name.encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except Exception:  # noqa: BLE001 - a name is a convenience
        pass


def start_zenoh_log() -> None:
    """Zenoh's own log (Rust's tracing writes it to stdout: a service's log file; a command run with ``--json``
    sends it to stderr, magmesh_cli/cli.py ``json_stdout``): errors by default, more with ``RUST_LOG``, e.g.
    ``RUST_LOG=warn,zenoh_transport=debug`` shows every link opened, closed or expired. Once per process."""
    global _LOG_STARTED
    if not _LOG_STARTED:
        import zenoh

        zenoh.init_log_from_env_or("error")
        _LOG_STARTED = True


def transport_tx() -> dict:
    """The ``transport/link/tx`` settings of every magmesh session and router (here and the secured mesh's)."""
    return {"lease": LEASE_MS, "keep_alive": KEEP_ALIVE,
            "queue": {"congestion_control": {"block": {"wait_before_close": WAIT_BEFORE_CLOSE_US}}}}


def default_endpoint() -> str:
    return os.environ.get("MAGMESH_ENDPOINT", DEFAULT_ENDPOINT)


def add_zenoh_args(parser: argparse.ArgumentParser) -> None:
    g = parser.add_argument_group("Zenoh")
    g.add_argument("--mode", "-m", choices=["peer", "client", "router"], default=None,
                   help="Zenoh session mode (default: client when connecting, else peer)")
    g.add_argument("--connect", "-e", action="append", default=None, metavar="ENDPOINT",
                   help=f"endpoint to connect to (repeatable; default {DEFAULT_ENDPOINT} or $MAGMESH_ENDPOINT)")
    g.add_argument("--listen", "-l", action="append", default=None, metavar="ENDPOINT",
                   help="endpoint to listen on (repeatable)")
    g.add_argument("--config", "-c", default=None, metavar="FILE", help="Zenoh JSON5 configuration file")
    g.add_argument("--cfg", action="append", default=None, metavar="KEY:VALUE",
                   help="a Zenoh configuration entry, VALUE in JSON5 (repeatable), e.g. transport/link/tx/lease:5000")
    g.add_argument("--multicast-scouting", action="store_true",
                   help="enable multicast scouting (off by default)")


def build_config(mode=None, connect=None, listen=None, config_file=None, cfg=None, multicast=False,
                 connect_timeout_s: float | None = None):
    """Build a :class:`zenoh.Config`.

    Services retry their connection for ever (they may start before their router); operator commands pass
    ``connect_timeout_s`` so that an endpoint nobody answers on is an error within that time."""
    import zenoh

    start_zenoh_log()
    conf = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    if connect is None and listen is None and mode is None and not config_file:
        connect = [default_endpoint()]
    if mode is None and not config_file:
        mode = "client" if connect and not listen else "peer"
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
        # keep retrying: a service may start before its router (operator commands: bounded)
        conf.insert_json5("connect/timeout_ms",
                          "-1" if connect_timeout_s is None else str(max(1, int(connect_timeout_s * 1000))))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if not config_file:
        conf.insert_json5("scouting/multicast/enabled", "true" if multicast else "false")
        tx = transport_tx()
        conf.insert_json5("transport/link/tx/lease", str(tx["lease"]))
        conf.insert_json5("transport/link/tx/keep_alive", str(tx["keep_alive"]))
        conf.insert_json5("transport/link/tx/queue/congestion_control/block/wait_before_close",
                          str(tx["queue"]["congestion_control"]["block"]["wait_before_close"]))
    for item in cfg or []:
        k, _, v = item.partition(":")
        if not k or not v:
            raise ValueError(f"--cfg {item!r} must be KEY:VALUE")
        conf.insert_json5(k, v)
    return conf


def config_from_args(args: argparse.Namespace, connect_timeout_s: float | None = None):
    return build_config(args.mode, args.connect, args.listen, args.config, args.cfg, args.multicast_scouting,
                        connect_timeout_s)


def where(args: argparse.Namespace) -> str:
    """The endpoints an operator command talks to, for messages."""
    if getattr(args, "connect", None):
        return ", ".join(args.connect)
    if getattr(args, "config", None):
        return f"the endpoints of {args.config}"
    return default_endpoint()


def open_client(args: argparse.Namespace, timeout_s: float, what: str = "magmesh"):
    """Open the Zenoh session of an operator command: the connection is bounded by ``timeout_s`` and Ctrl-C
    works while it is attempted (the blocking open runs on a helper thread). Raises
    :class:`magmesh.errors.UserError` (exit 1) when nothing answers or the configuration is refused."""
    import threading

    import zenoh

    from .errors import UserError

    try:
        conf = config_from_args(args, connect_timeout_s=timeout_s)
    except Exception as e:
        raise UserError(f"{what}: bad Zenoh configuration: {e}", 2) from None
    box: dict = {}
    done = threading.Event()

    def _open() -> None:
        try:
            box["session"] = zenoh.open(conf)
        except Exception as e:  # noqa: BLE001 - reported below as one paragraph
            box["error"] = e
        finally:
            done.set()

    threading.Thread(target=_open, name="zenoh-open", daemon=True).start()
    if timeout_s > 5.0 and not done.wait(2.0):  # a long wait says what it waits for
        print(f"{what}: connecting to {where(args)} (up to {timeout_s:g} s; Ctrl-C stops) ...", file=sys.stderr,
              flush=True)
    if not done.wait(timeout_s + 5.0):
        raise UserError(f"{what}: could not connect to {where(args)} within {timeout_s:g} s. Is the mesh running "
                        f"(magmesh up) and is the endpoint right? Use --connect ENDPOINT, --timeout S.", 1)
    if "error" in box:
        detail = str(box["error"]).split(" at /", 1)[0]
        raise UserError(f"{what}: could not connect to {where(args)} within {timeout_s:g} s ({detail}). Is the mesh "
                        f"running (magmesh up) and is the endpoint right? Use --connect ENDPOINT, --timeout S.", 1)
    return box["session"]


def control_priority():
    """Zenoh priority of the control plane (status, alarm and control queries; a reply takes its query's):
    above the data's default, so an overloaded link still carries them ahead of its queued frames."""
    import zenoh

    return zenoh.Priority.INTERACTIVE_HIGH


def control_request(session, role: str, instance: str, req: dict, timeout: float) -> dict | None:
    """Ask an instance's control key (``magmesh/svc/{role}/{instance}/control``); its reply when it answered
    ``ok``, else None (no answer within ``timeout`` s, a refusal, or a reply that is not a msgpack map)."""
    import msgpack

    from schemas import keys

    payload = msgpack.packb(req, use_bin_type=True)
    for rep in session.get(keys.svc_control(role, instance), payload=payload, timeout=timeout,
                           priority=control_priority()):
        if rep.ok is not None:
            try:
                res = msgpack.unpackb(rep.ok.payload.to_bytes(), strict_map_key=False)
            except Exception:  # noqa: BLE001 - any undecodable reply is no answer
                return None
            return res if isinstance(res, dict) and res.get("ok") else None
    return None
