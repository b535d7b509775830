"""The ``magmesh`` command. Sub-commands live in :mod:`magmesh.commands` (one module each, with
``register(subparsers)``); they are discovered at start-up."""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from schemas.keys import KeyError_

from . import __version__, commands
from .errors import UserError


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


def main(argv: list[str] | None = None) -> int:
    parser = build_parser(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        rc = args.func(args)
    except UserError as e:
        text = str(e)
        print(text if text.startswith("magmesh") else f"magmesh {args.command}: {text}", file=sys.stderr, flush=True)
        return e.code
    except KeyError_ as e:  # a bad name (role, instance, vehicle) given on the command line
        print(f"magmesh {args.command}: {e}", file=sys.stderr, flush=True)
        return 2
    except KeyboardInterrupt:
        # Ctrl-C during a blocking Zenoh call: leave at once (a helper thread may still be inside Zenoh)
        print(f"magmesh {args.command}: interrupted", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(130)
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
