"""``magmesh rerun``: run services again on a recording, in a private mesh, and record what they say.

    magmesh rerun drive.mcap --service "services.dmc_detector --impl fcm" -o rerun.mcap --report report/

Starts its own Zenoh router on a free loopback port (the live mesh is not touched, so vehicle ids need no
remapping), the given services as processes connected to it, and a recorder; replays the recording's
input keys (default ``magmesh/*/clean/**`` and ``magmesh/*/cal/**``) as fast as the services take them;
waits until their outputs settle; stops everything. With ``--report`` it writes a report of the original
recording with the outputs the re-run produced in place of the recorded ones.
"""

from __future__ import annotations

import argparse
import logging
import os
import shlex
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from magmesh.paths import DEPLOY_DIR, REPO
from schemas import keys

from ..recording import matches_any, parse_rate, summarize

log = logging.getLogger("magmesh.rerun")

DEFAULT_INPUTS = ("magmesh/*/clean/**", "magmesh/*/cal/**")


def register(subparsers) -> None:
    p = subparsers.add_parser("rerun", help="run services again on a recording in a private mesh",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="MCAP recording to replay")
    p.add_argument("--service", action="append", required=True, metavar="'MODULE [ARGS]'",
                   help="a service to run, e.g. 'services.dmc_detector --impl fcm' (repeatable)")
    p.add_argument("-o", "--output", required=True, help="MCAP file for what the services publish")
    p.add_argument("--keys", nargs="+", default=list(DEFAULT_INPUTS), metavar="KEYEXPR",
                   help=f"input keys to replay (default {' '.join(DEFAULT_INPUTS)})")
    p.add_argument("--rate", default="max", help="replay speed factor or 'max' (default)")
    p.add_argument("--manifest", default=str(DEPLOY_DIR / "mesh.toml"), help="vehicle tables for the services")
    p.add_argument("--report", default=None, metavar="DIR", help="also write a report of the re-run")
    p.add_argument("--settle", type=float, default=2.0, metavar="S",
                   help="outputs are complete when nothing new arrived for S seconds (default 2)")
    p.set_defaults(func=run)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rerun(
    path: str | Path,
    services: Sequence[str],
    output: str | Path,
    input_keys: Sequence[str] = DEFAULT_INPUTS,
    rate: float = 0.0,
    manifest: str | Path | None = None,
    settle_s: float = 2.0,
    start_timeout_s: float = 30.0,
) -> dict:
    """Replay ``input_keys`` of a recording through ``services`` (``"module args…"`` each) in a private mesh;
    record everything else they publish to ``output``. Returns replay and recording counts."""
    import zenoh

    from magmesh.zconf import build_config

    from .record import record
    from .replay import replay_to_mesh

    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    router = zenoh.open(build_config(mode="router", listen=[endpoint]))
    procs: list[subprocess.Popen] = []
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    try:
        for spec in services:
            module, *args = shlex.split(spec)
            cmd = [sys.executable, "-m", module, "--connect", endpoint, *args]
            if manifest and "--manifest" not in args:
                cmd += ["--manifest", str(manifest)]
            procs.append(subprocess.Popen(cmd, cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE))
        # every service up: its liveliness token is visible on the router
        deadline = time.monotonic() + start_timeout_s
        while True:
            tokens = [str(r.ok.key_expr) for r in router.liveliness().get(f"{keys.ROOT}/{keys.SVC}/**", timeout=1.0)
                      if r.ok is not None]
            if len(tokens) >= len(services):
                break
            for p, spec in zip(procs, services, strict=True):
                if p.poll() is not None:
                    raise RuntimeError(f"{spec} exited: {p.stderr.read().decode()[-2000:]}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"services not up after {start_timeout_s:g} s (tokens seen: {tokens})")
            time.sleep(0.2)
        time.sleep(0.5)  # subscriptions declared with the token are routed by now
        stop, ready = threading.Event(), threading.Event()
        progress: dict = {}
        result: dict = {}
        rec_thread = threading.Thread(target=lambda: result.update(counts=record(
            build_config(connect=[endpoint]), output, [keys.everything()], stop=stop, ready=ready,
            on_progress=progress.update, exclude=input_keys)), daemon=True)
        rec_thread.start()
        if not ready.wait(15):
            raise RuntimeError("recorder did not start")
        stats = replay_to_mesh(build_config(connect=[endpoint]), path, rate, list(input_keys), wait_subscribers_s=5.0)
        # outputs are complete when the recorder has seen nothing new for settle_s
        last, since = -1, time.monotonic()
        while time.monotonic() - since < settle_s + 1.0:
            n = progress.get("written", 0) + progress.get("skipped", 0)
            if n != last:
                last, since = n, time.monotonic()
            time.sleep(0.2)
        stop.set()
        rec_thread.join(30)
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
        router.close()
    return {"replay": stats.as_dict(), "recorded": result.get("counts", {})}


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    src = Path(args.input)
    if not src.exists():
        raise SystemExit(f"magmesh rerun: {src} does not exist")
    try:
        rate = parse_rate(args.rate)
    except ValueError as e:
        raise SystemExit(f"magmesh rerun: {e}") from None
    res = rerun(src, args.service, args.output, args.keys, rate, args.manifest, args.settle)
    rp, rc_ = res["replay"], res["recorded"]
    print(f"replayed {rp['published']} messages on {rp['keys']} keys in {rp['wall_s']:.1f} s; "
          f"recorded {rc_.get('written', 0)} output messages on {rc_.get('keys', 0)} keys to {args.output}")
    for k, n in rc_.get("per_key", {}).items():
        print(f"  {k}  {n}")
    if args.report:
        from .report import make_report

        produced = list(summarize(args.output)["keys"])
        index = make_report([src, Path(args.output)], args.report, manifest=args.manifest,
                            exclude=[k for k in produced if not matches_any(args.keys, k)],
                            title=f"{src.stem} re-run through {', '.join(args.service)}")
        print(f"report written: {index.resolve()}")
    return 0
