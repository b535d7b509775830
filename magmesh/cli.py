"""The ``magmesh`` command. Sub-commands live in :mod:`magmesh.commands` (one module each, with
``register(subparsers)``); they are discovered at start-up."""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from . import __version__, commands
from .errors import UserError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="magmesh", description="Distributed magnetic sensing for navigation over Zenoh.")
    p.add_argument("--version", action="version", version=f"magmesh {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND")
    for mod in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        if mod.name.startswith("_"):
            continue
        m = importlib.import_module(f"{commands.__name__}.{mod.name}")
        if hasattr(m, "register"):
            m.register(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
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
    except KeyboardInterrupt:
        # Ctrl-C during a blocking Zenoh call: leave at once (a helper thread may still be inside Zenoh)
        print(f"magmesh {args.command}: interrupted", file=sys.stderr, flush=True)
        sys.stdout.flush()
        os._exit(130)
    return int(rc or 0)


if __name__ == "__main__":
    sys.exit(main())
