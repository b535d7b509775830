"""The ``magmesh`` command. Sub-commands live in :mod:`magmesh_cli.commands` (one module each, with
``register(subparsers)``); they are discovered at start-up."""

from __future__ import annotations

import argparse
import importlib
import logging
import math
import os
import pkgutil
import re
import signal
import sys
import threading

from magmesh import __version__
from magmesh.errors import UserError
from schemas.keys import KeyError_

from . import commands


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; given ``argv`` naming a command, only that command's module is imported (each module's
    top-level command has the module's name), so ``magmesh status`` does not pay for plotting imports."""
    p = argparse.ArgumentParser(prog="magmesh", description="Distributed magnetic sensing for navigation over Zenoh.")
    p.add_argument("--version", action="version", version=f"magmesh {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    names = sorted(m.name for m in pkgutil.iter_modules(commands.__path__) if not m.name.startswith("_"))
    first = next((a for a in (argv or []) if not a.startswith("-")), None)
    if argv is not None and first is not None and first.replace("-", "_") in names:
        names = [first.replace("-", "_")]  # ros2-bridge lives in ros2_bridge.py
    for name in names:
        m = importlib.import_module(f"{commands.__name__}.{name}")
        if hasattr(m, "register"):
            m.register(sub)
    return p


_ENDPOINT = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*/\S+$")


def command_names() -> list[str]:
    return sorted(m.name.replace("_", "-") for m in pkgutil.iter_modules(commands.__path__)
                  if not m.name.startswith("_"))


def check_common_args(args: argparse.Namespace) -> str | None:
    """A mistake in the options every command shares (seconds, endpoints), as one sentence; None when fine."""
    for name in ("duration", "timeout"):
        v = getattr(args, name, None)
        if v is None or isinstance(v, bool) or not isinstance(v, (int, float)):
            continue
        if not math.isfinite(v) or v < 0 or (name == "timeout" and v == 0):
            return (f"--{name} {v:g} is not a number of seconds it can use: give a finite number "
                    f"{'> 0' if name == 'timeout' else '≥ 0'}, e.g. --{name} 30.")
    for name in ("connect", "listen", "endpoint"):
        v = getattr(args, name, None)
        for ep in ([v] if isinstance(v, str) else v or []):
            if isinstance(ep, str) and not _ENDPOINT.match(ep):
                return (f"endpoint {ep!r} (--{name}) is not valid: an endpoint is PROTOCOL/ADDRESS, for example "
                        f"tcp/127.0.0.1:7447.")
    return None


def _terminated(signum, frame) -> None:
    raise KeyboardInterrupt


def json_stdout() -> None:
    """With ``--json`` the command's stdout carries its JSON alone: whatever else writes to file descriptor 1 goes
    to stderr — Zenoh's own log among them (Rust's tracing writes there, e.g. a "timer overrun" under load, which
    once made a benchmark's JSON unreadable), and programs started with the process's stdout. Python's print still
    reaches the real stdout."""
    try:
        if sys.stdout is None or sys.stdout.fileno() != 1:
            return  # (done before)
    except (AttributeError, OSError, ValueError):  # (stdout replaced: a test's capture)
        return
    sys.stdout.flush()
    keep = os.dup(1)
    os.dup2(2, 1)
    sys.stdout = os.fdopen(keep, "w", encoding="utf-8", errors="backslashreplace", buffering=1)


def main(argv: list[str] | None = None) -> int:
    argv_ = sys.argv[1:] if argv is None else argv
    first = next((a for a in argv_ if not a.startswith("-")), None)
    if argv_ and not argv_[0].startswith("-") and first not in command_names():
        # without importing every command's module (plots, bridges: slow to import on a loaded machine)
        print(f"magmesh: unknown command {first!r}; the commands are {', '.join(command_names())} "
              f"(magmesh --help says what each does).", file=sys.stderr, flush=True)
        return 2
    parser = build_parser(argv_)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    problem = check_common_args(args)
    if problem is not None:
        print(f"magmesh {args.command}: {problem}", file=sys.stderr, flush=True)
        return 2
    if getattr(args, "json", False) is True:
        json_stdout()
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL and threading.current_thread() is threading.main_thread():
        # SIGTERM (kill, a job's timeout) ends a command as Ctrl-C does: what it started is stopped on the way out
        # (a benchmark's or an evaluation's services run in sessions of their own, which no signal to this
        # process reaches; killed outright they were left running). Commands with their own handler replace it.
        signal.signal(signal.SIGTERM, _terminated)
    try:
        rc = args.func(args)
    except UserError as e:
        text = str(e)
        print(text if text.startswith("magmesh") else f"magmesh {args.command}: {text}", file=sys.stderr, flush=True)
        return e.code
    except KeyError_ as e:  # a bad name (role, instance, vehicle) given on the command line
        print(f"magmesh {args.command}: {e}", file=sys.stderr, flush=True)
        return 2
    except Exception as e:
        if not type(e).__module__.startswith("mcap."):
            raise
        # a file that is not an MCAP recording (or a damaged one) given to replay, report, rerun, mcap
        print(f"magmesh {args.command}: a file given is not a readable MCAP recording ({type(e).__name__}: {e}). "
              f"Give a file written by magmesh record (run.mcap).", file=sys.stderr, flush=True)
        return 1
    except KeyboardInterrupt:
        # Ctrl-C during a blocking Zenoh call: leave at once (a helper thread may still be inside Zenoh)
        print(f"magmesh {args.command}: interrupted", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(130)
    return int(rc or 0)


#: set by a command that has stopped everything it started (``magmesh up``): the process then leaves without the
#: interpreter's finalisation, which can abort it (glibc "FATAL: exception not rethrown", exit −6) when a daemon
#: thread is still inside a Zenoh call, turning a clean exit code into a crash
EXIT_WITHOUT_FINALISING = False


def run_main() -> None:
    """The process entry point (``magmesh`` and ``python -m magmesh``)."""
    rc = main()
    if EXIT_WITHOUT_FINALISING:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(rc)
    sys.exit(rc)


if __name__ == "__main__":
    run_main()
