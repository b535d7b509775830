"""``magmesh bench mesh``: throughput, latency, CPU and loss of the real mesh against the raw-Zenoh limit."""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="benchmarks (mesh: real processes under N vehicles vs the raw-Zenoh limit)")
    bsub = p.add_subparsers(dest="bench_name", metavar="NAME")
    m = bsub.add_parser("mesh", help="the whole pipeline under N simulated vehicles, against the no-processing limit")
    m.add_argument("--vehicles", default="10,50,200,500",
                   help="comma-separated vehicle counts for the scaling table (default 10,50,200,500)")
    m.add_argument("--duration", type=float, default=15.0,
                   help="seconds of load per run, measured after the warm-up (paced runs)")
    m.add_argument("--warmup", type=float, default=10.0,
                   help="seconds each paced run publishes before latency and CPU are measured (meeting the fleet: "
                        "its latency is reported apart as warm-up p99; every sample counts for loss)")
    m.add_argument("--repeat", type=int, default=3, help="runs per case; figures are medians")
    m.add_argument("--saturation-vehicles", type=int, default=None,
                   help="vehicles for the pipeline-vs-limit throughput run (default: the smallest count, ≥ 10)")
    m.add_argument("--stages", default=None, help="comma-separated stages (default: all available)")
    m.add_argument("--wire", choices=("v1", "v2", "v3"), default="v3",
                   help="v3 (default): each vehicle publishes one batch per window with binary columns, ingest "
                        "emits fleet frames; v2: the same with list columns; v1: every sample alone on its key, end "
                        "to end")
    m.add_argument("--window", type=float, default=0.05,
                   help="v2: seconds of samples per vehicle batch (default 0.05)")
    m.add_argument("--frame-window", type=float, default=0.02,
                   help="v2/v3: ingest's fleet frame window, s (default 0.02: every window costs each stage process a "
                        "fixed amount, which two processes per stage on two cores could not afford at 0.01)")
    m.add_argument("--p99-ms", type=float, default=100.0,
                   help="latency goal a sustained row must meet, raw publish → dmc out p99 (default 100 ms)")
    m.add_argument("--no-v1-ingest", action="store_true",
                   help="skip measuring how many v1 single-sample vehicles one ingest sustains")
    m.add_argument("--no-overload", action="store_true",
                   help="skip the overload run (twice the highest sustained load, then back to it)")
    m.add_argument("--overload-vehicles", type=int, default=None,
                   help="the load the overload run doubles (default: the highest sustained count)")
    m.add_argument("--instances", default="1",
                   help="comma-separated counts of instances per stage: the scaling table once per count, each stage "
                        "a group of that many members sharing the vehicles (e.g. 1,2; default 1)")
    m.add_argument("--sink", choices=("frames", "keys"), default="frames",
                   help="where the bench counts the DMC's outputs (v2/v3): frames (default) — its fleet frames, as "
                        "a fleet-wide consumer takes them, the per-vehicle dmc keys then watched by nobody and not "
                        "put; keys — every vehicle's dmc key (magmesh/*/dmc), one message per vehicle per epoch")
    m.add_argument("--json", action="store_true")
    m.set_defaults(func=run_mesh)
    c = bsub.add_parser("cores", help="each pure core against its Python peer on the same input")
    c.add_argument("--json", action="store_true")
    c.set_defaults(func=run_cores)
    p.set_defaults(func=lambda a: (p.print_help(), 2)[1])


def run_cores(args: argparse.Namespace) -> int:
    from bench.cores_bench import run_all

    res = run_all(progress=lambda s: print(s, file=sys.stderr, flush=True))
    print(json.dumps(res) if args.json else json.dumps(res, indent=2, default=str))
    return 0


def run_mesh(args: argparse.Namespace) -> int:
    from bench.mesh_bench import bench, format_text

    vehicles = [int(x) for x in args.vehicles.split(",") if x.strip()]
    stages = tuple(s.strip() for s in args.stages.split(",")) if args.stages else None
    try:
        instances = tuple(int(x) for x in args.instances.split(",") if x.strip())
    except ValueError:
        instances = ()
    if not instances or any(not 1 <= k <= 64 for k in instances):
        print(f"magmesh bench mesh: --instances takes counts from 1 to 64 separated by commas (e.g. 1,2), not "
              f"{args.instances!r}", file=sys.stderr)
        return 2
    if not 0 <= args.warmup <= 600 or not 0 < args.duration <= 3600:
        print(f"magmesh bench mesh: --warmup takes 0 to 600 s and --duration more than 0 up to 3600 s (given "
              f"{args.warmup:g} and {args.duration:g})", file=sys.stderr)
        return 2
    try:
        res = bench(vehicles, args.duration, args.repeat, stages, args.saturation_vehicles,
                    progress=lambda s: print(s, file=sys.stderr, flush=True), wire=args.wire, window_s=args.window,
                    frame_s=args.frame_window, p99_ms=args.p99_ms, v1_ingest=not args.no_v1_ingest,
                    overload=not args.no_overload, overload_vehicles=args.overload_vehicles, instances=instances,
                    warmup_s=args.warmup, sink=args.sink)
    except RuntimeError as e:  # a run whose stages did not come up or whose groups did not form
        print(f"magmesh bench mesh: the run stopped: {e}. The stages' logs are in that directory; a stage that "
              "did not come up within 30 s usually failed at start (its log says why) or the machine was too busy "
              "to start it; run the bench again on a quieter machine or with fewer vehicles.", file=sys.stderr)
        return 1
    if args.json:
        json.dump(res, sys.stdout)
        print()
    else:
        print(format_text(res))
    return 0
