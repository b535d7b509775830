"""``magmesh eval NAME [--json]``: run an evaluation from ``bench/eval_NAME.py``."""

from __future__ import annotations

import argparse
import importlib
import json
import pkgutil
import sys


def _evals() -> dict:
    import bench

    found = {}
    for mod in pkgutil.iter_modules(bench.__path__):
        if mod.name.startswith("eval_"):
            found[mod.name[5:]] = f"bench.{mod.name}"
    return found


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("eval", help="run an evaluation (accuracy against truth, real data and peers)")
    esub = p.add_subparsers(dest="eval_name", metavar="NAME")
    for name, modname in sorted(_evals().items()):
        mod = importlib.import_module(modname)
        ep = esub.add_parser(name, help=(mod.__doc__ or "").strip().splitlines()[0] if mod.__doc__ else name)
        ep.add_argument("--json", action="store_true", help="print one JSON object with every figure")
        if hasattr(mod, "add_arguments"):
            mod.add_arguments(ep)
        ep.set_defaults(func=lambda a, _m=mod: _run(_m, a))
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])


def _run(mod, args: argparse.Namespace) -> int:
    result = mod.run(args)
    if args.json:
        json.dump(result, sys.stdout)
        print()
    elif hasattr(mod, "format_text"):
        print(mod.format_text(result))
    else:
        print(json.dumps(result, indent=2))
    return 0
