"""Elastic roles on the live mesh: the DMC detector as a group (``instances = 3`` under ``magmesh up``) serving a
fleet of simulated cars, one member killed with SIGKILL (the survivors take its vehicles over from its journal
and alarm file; the supervisor restarts it and it takes its vehicles back by hand-over), then ``magmesh scale``
to 4 and down to 2. What the mesh carried is checked from outside (bench/elastic_run.py): no dmc output
repeated, every missing epoch counted, no alarm transition lost or repeated, and the transitions of every vehicle
moved only by hand-overs equal those of one detector fed every epoch offline."""

from __future__ import annotations

import pytest
from meshutil import free_port

from bench.elastic_run import run_scenario, vehicle_ids

pytestmark = pytest.mark.mesh


def _check(res: dict, n_vehicles: int, n_kills: int, final_members: list[str]) -> None:
    assert not res["problems"], "\n".join(res["problems"])
    f = res["figures"]
    kills = [e for e in res["events"] if e["step"] == "kill"]
    assert len(kills) == n_kills and all(k["vehicles"] for k in kills), kills  # each kill hit a member with vehicles
    assert all(k["takeover_s"] != float("inf") for k in kills), kills  # every vehicle of a dead member resumed
    assert f["reference_transitions_compared"] > 0, "no alarm transition to compare: the move check is vacuous"
    assert f["duplicates"] == 0 and f["repeated_alarm_transitions"] == 0 and f["lost_alarm_transitions"] == 0, f
    if n_kills <= 1:
        assert f["epochs_missing"] == f["lost_in_takeover"] + sum(f["upstream_gap_per_vehicle"].values()) \
            + f["seq_missing"], f
    for e in res["events"]:
        if e["step"] == "scale":
            assert e["reply"]["ok"] and all(e["reply"]["handed_over"].values()), e["reply"]
    # magmesh status (the command) and the supervisor show the assignment: each vehicle held once, none without
    groups = res["status_cli"]["groups"]["dmc_detector/dmc"]
    held = sorted(v for vs in groups["vehicles"].values() for v in vs)
    assert held == vehicle_ids(n_vehicles) and not groups["unowned"] and not groups["duplicates"], groups
    assert sorted(groups["vehicles"]) == final_members, groups
    sup = res["supervisor"]["groups"]["dmc"]
    assert sup["instances"] == final_members and not sup["unowned"] and not sup["duplicates"], sup
    print(f"\nelastic: {n_vehicles} cars, {f['dmc_outputs']} dmc outputs; kills: "
          + ", ".join(f"{k['instance']} holding {len(k['vehicles'])} (outputs resumed after {k['takeover_s']:.2f} s)"
                      for k in kills)
          + f"; epochs missing {f['epochs_missing']} = lost_in_takeover {f['lost_in_takeover']} + upstream_gap "
            f"{f['upstream_gap_per_vehicle']} + never out of a killed process {f['seq_missing']}; {f['alarm_transitions']} alarm transitions, "
            f"{f['reference_transitions_compared']} of moved-only vehicles equal to one detector's")


def test_group_of_three_survives_a_kill_and_scales_to_four_and_two(tmp_path):
    # the fleet drives until the steps are done (then 2 s more): the run takes what the machine needs for them
    # (40-80 s here, with the load average at 7-19 from other work; 10 of 10 runs passed before it came back to the
    # default suite)
    res = run_scenario(tmp_path, 6, 3, [("wait", 2), ("kill",), ("scale", 4), ("scale", 2)], duration_s=600.0,
                       port=free_port(), seed=5, end_after_steps_s=2.0)
    _check(res, 6, 1, ["dmc-1", "dmc-2"])


def test_members_with_their_own_state_take_a_killed_members_vehicles_from_what_the_mesh_showed(tmp_path):
    """As on different hosts: each member has a state directory of its own, so the survivors cannot read a killed
    member's journal or alarm file; they go on from what the mesh showed (its fleet frames, alarm transitions and
    last answer), then the killed member is started again with its own state. Before, the same run repeated outputs (seqs started again), repeated alarm transitions and left
    every missing epoch uncounted (12 cars: 6 outputs and 2 transitions repeated, 152 epochs missing, 0 counted)."""
    res = run_scenario(tmp_path, 6, 3, [("wait", 2), ("kill",)], duration_s=600.0, port=free_port(), seed=5,
                       end_after_steps_s=2.0, split_state=True)
    assert not res["problems"], "\n".join(res["problems"])
    f = res["figures"]
    kills = [e for e in res["events"] if e["step"] == "kill"]
    assert len(kills) == 1 and kills[0]["vehicles"] and kills[0]["takeover_s"] != float("inf"), kills
    assert f["duplicates"] == 0 and f["repeated_alarm_transitions"] == 0 and f["lost_alarm_transitions"] == 0, f
    assert f["epochs_missing"] == f["lost_in_takeover"] + sum(f["upstream_gap_per_vehicle"].values()) \
        + f["seq_missing"], f
    # the survivors took its vehicles from the mesh; started again on its own "host", it took its share back by
    # hand-over (status: each vehicle held once)
    stats = [st["group"] for st in res["final"].values() if "group" in st]
    assert len(stats) == 3 and sum(g["failovers_from_mesh"] for g in stats) == len(kills[0]["vehicles"]), stats
    assert sum(g["unrecovered"] for g in stats) == 0 and kills[0]["rejoined_settled"], (stats, kills)


@pytest.mark.slow  # 2-3 min: four kills -9 and three scalings of 12 cars (6 of 6 runs passed, load average 2-10)
def test_group_kills_and_scaling_long(tmp_path):
    # the last kill spares vehicles no kill touched (with four random kills of 12 cars, all 12 were touched in two
    # runs, and the comparison with one detector had nothing left to compare)
    steps = [("wait", 2), ("kill",), ("scale", 1), ("wait", 3), ("scale", 4), ("kill",), ("kill",), ("scale", 2),
             ("kill", "spare")]
    res = run_scenario(tmp_path, 12, 3, steps, duration_s=1200.0, port=free_port(), seed=13, end_after_steps_s=3.0)
    _check(res, 12, 4, ["dmc-1", "dmc-2"])
