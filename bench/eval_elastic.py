"""Elastic roles under load: a fleet of simulated cars, the DMC detector as a group; kills and live scaling.

Two runs on the live mesh (``magmesh up``, one router on loopback, each process real), everything checked from
outside on what subscribers saw (bench/elastic_run.py):

- ``kill``: ``--cars`` cars (30), 3 instances; ``--kills`` (10) times, after a seeded random wait, SIGKILL of a
  member holding vehicles (chosen with the seed); the survivors take its vehicles over from its journal and
  alarm file, the supervisor restarts it and it takes its own back by hand-over. ``takeover_s``: from the kill
  until every vehicle it held has a dmc output again (arrival at a subscriber); the 2 s target is on the max.
- ``scale``: the same fleet, 1 instance, then ``magmesh scale dmc 4`` and ``magmesh scale dmc 2`` under load.
- ``one`` (``--one`` or ``--only one``): the sanity case, 1 instance on the same fleet and no move; its output lag
  (arrival minus sample time) says whether one instance keeps up.

Per run: dmc outputs repeated (``duplicates``), dmc seq gaps seen (``seq_missing``: outputs a killed process had
sent that never left it) against epochs missing (a pair of clean samples without an output) and epochs counted
``lost_in_takeover`` by the new owners; alarm transitions lost (seq gap) or repeated (same state twice); and, for
every vehicle no kill touched (moved only by hand-overs), whether its alarm transitions equal those of one
detector fed every epoch offline (the service's own code on the same samples): a move that caused or hid a
transition shows there. ``--quick`` runs 10 cars and 3 kills (a smoke check, not the figures of the README).

``--split-state``: the kill run with each member started by hand with a state directory of its own, as members on
different hosts (no supervisor: the run starts a killed member again itself, on its own "host"): a survivor cannot
read the dead member's journal or alarm file and goes on from what the mesh showed of its vehicles (their outputs'
seqs and times in its fleet frames, its alarm transitions, its last answer to the group's rounds). The scale run
needs the supervisor and is not part of it.

``--frames``: the fleet publishes raw batches to an ingest process with ``output = "frames"``, and the members take
its fleet frames (cut to the vehicles each holds); besides the checks above, each member's dmc frames must carry
exactly the dmc rows it published (``dmc_rows_in_two_frames``, ``dmc_frame_rows_not_published``,
``dmc_published_not_in_frames``).
"""

from __future__ import annotations

import argparse
import random
import statistics
import tempfile
from pathlib import Path

from bench.elastic_run import run_scenario


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--cars", type=int, default=30, help="simulated cars (default 30)")
    p.add_argument("--kills", type=int, default=10, help="SIGKILLs in the kill run (default 10)")
    p.add_argument("--seed", type=int, default=7, help="seed of the kill moments and victims (default 7)")
    p.add_argument("--only", choices=("kill", "scale", "one"), default=None,
                   help="run only one of them (one: the sanity run, 1 instance, no move; not in the default set)")
    p.add_argument("--one", action="store_true", help="also the sanity run: 1 instance on the same fleet, no move")
    p.add_argument("--one-s", type=float, default=40.0, help="seconds of the sanity run (default 40)")
    p.add_argument("--quick", action="store_true", help="10 cars, 3 kills")
    p.add_argument("--frames", action="store_true",
                   help="the fleet through ingest as fleet frames (output = frames): the members take frames")
    p.add_argument("--split-state", action="store_true",
                   help="the kill run with a state directory per member, as on different hosts (no scale run)")
    p.add_argument("--keep", default=None, metavar="DIR", help="keep logs, state and what the subscribers saw in DIR")


def _summary(res: dict) -> dict:
    f = dict(res["figures"])
    f["problems"] = res["problems"]
    f["events"] = [{k: v for k, v in e.items() if k not in ("assignment", "reply", "t_wall")} |
                   ({"reply_ok": e["reply"].get("ok"), "handed_over": e["reply"].get("handed_over"),
                     "took_s": e["reply"].get("took_s")} if "reply" in e else {}) for e in res["events"]]
    groups = (res.get("status_cli") or {}).get("groups", {}).get("dmc_detector/dmc", {})
    f["final_unowned"] = groups.get("unowned")
    f["final_duplicates"] = groups.get("duplicates")
    f["fleet"] = res.get("fleet")
    f["load_avg"] = res.get("load_avg")
    return f


def run(args: argparse.Namespace) -> dict:
    cars, kills = (10, 3) if args.quick else (args.cars, args.kills)
    rng = random.Random(args.seed)
    base = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="magmesh-eval-elastic-"))
    split = bool(getattr(args, "split_state", False))
    if split and args.frames:
        raise SystemExit("magmesh eval elastic: --split-state starts the members by hand and no ingest process, so it "
                         "cannot run with --frames; run the two separately.")
    out: dict = {"cars": cars, "seed": args.seed, "frames": args.frames, "split_state": split}
    if args.only in (None, "kill"):
        steps: list[tuple] = [("wait", 2.0)]
        for _ in range(kills):
            steps += [("wait", round(rng.uniform(1.0, 6.0), 2)), ("kill",)]
        res = run_scenario(base / "kill", cars, 3, steps, duration_s=3600.0, seed=args.seed, end_after_steps_s=3.0,
                           save_data=bool(args.keep), frames=args.frames, split_state=split)
        k = _summary(res)
        t = [e["takeover_s"] for e in res["events"] if e["step"] == "kill"]
        groups = [st["group"] for st in res["final"].values() if "group" in st]
        k["failovers_from_mesh"] = sum(g.get("failovers_from_mesh", 0) for g in groups)
        k["unrecovered"] = sum(g.get("unrecovered", 0) for g in groups)
        k.update(kills=len(t), takeover_s=t, takeover_s_max=max(t) if t else None,
                 takeover_s_median=statistics.median(t) if t else None,
                 takeover_within_2s=sum(1 for x in t if x <= 2.0))
        out["kill"] = k
    if args.only in (None, "scale") and not split:
        steps = [("wait", 5.0), ("scale", 4), ("wait", 5.0), ("scale", 2), ("wait", 5.0)]
        res = run_scenario(base / "scale", cars, 1, steps, duration_s=3600.0, seed=args.seed, end_after_steps_s=3.0,
                           save_data=bool(args.keep), frames=args.frames)
        out["scale"] = _summary(res)
    if args.only == "one" or (args.only is None and args.one):
        res = run_scenario(base / "one", cars, 1, [("wait", args.one_s)], duration_s=3600.0, seed=args.seed,
                           end_after_steps_s=1.0, save_data=bool(args.keep), frames=args.frames)
        out["one"] = _summary(res)
    if "kill" in out:  # the names, at the top
        out["takeover_s_max"] = out["kill"]["takeover_s_max"]
    runs = [out[r] for r in ("kill", "scale", "one") if r in out]
    out["lost_alarm_transitions"] = sum(r["lost_alarm_transitions"] for r in runs)
    out["repeated_alarm_transitions"] = sum(r["repeated_alarm_transitions"] for r in runs)
    out["work_dir"] = str(base)
    return out


def format_text(r: dict) -> str:
    lines = [f"elastic roles: {r['cars']} cars, seed {r['seed']}"
             + (", through ingest as fleet frames" if r.get("frames") else "")
             + (", a state directory per member (as on different hosts)" if r.get("split_state") else "")]
    k = r.get("kill")
    if k:
        lines.append(f"  kill: {k['kills']} SIGKILLs of a member of 3; takeover (outputs resumed) max "
                     f"{k['takeover_s_max']:.2f} s, median {k['takeover_s_median']:.2f} s, {k['takeover_within_2s']}"
                     f"/{k['kills']} within 2 s")
        lines.append(f"        epochs missing {k['epochs_missing']} = lost_in_takeover {k['lost_in_takeover']} + "
                     f"sent but never out of a killed process {k['seq_missing']}; duplicates {k['duplicates']}; alarm "
                     f"transitions {k['alarm_transitions']}: lost {k['lost_alarm_transitions']}, repeated "
                     f"{k['repeated_alarm_transitions']}; vehicles moved only by hand-over: "
                     f"{k['transitions_changed_by_moves']} differ from one detector "
                     f"({k['reference_transitions_compared']} transitions compared); failovers from what the mesh "
                     f"showed {k.get('failovers_from_mesh', 0)}, unrecovered {k.get('unrecovered', 0)}")
    s = r.get("scale")
    if s:
        took = [e.get("took_s") for e in s["events"] if e["step"] == "scale"]
        settle = [e.get("settle_s") for e in s["events"] if e["step"] == "scale"]
        lines.append(f"  scale 1 -> 4 -> 2: seq gaps {s['seq_missing']}, duplicates {s['duplicates']}, epochs missing "
                     f"{s['epochs_missing']}; alarm transitions {s['alarm_transitions']}: lost "
                     f"{s['lost_alarm_transitions']}, repeated {s['repeated_alarm_transitions']}, "
                     f"{s['transitions_changed_by_moves']} vehicles differ from one detector "
                     f"({s['reference_transitions_compared']} transitions compared); scale replies {took} s, "
                     f"settled after {settle} s")
    o = r.get("one")
    if o:
        lines.append(f"  one instance, no move: seq gaps {o['seq_missing']}, duplicates {o['duplicates']}, epochs missing "
                     f"{o['epochs_missing']}; output lag p50 {o['lag_s_p50']} s, p99 {o['lag_s_p99']} s, max "
                     f"{o['lag_s_max']} s (last 10 s p50 {o['lag_s_last10_p50']} s)")
    for name in ("kill", "scale", "one"):
        for p in (r.get(name) or {}).get("problems", []):
            lines.append(f"  problem ({name}): {p[:400]}")
    return "\n".join(lines)
