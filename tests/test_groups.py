"""Rendezvous assignment of vehicles to a group's live members (magmesh/groups.py)."""

import random
import subprocess
import sys

from magmesh import groups

CARS = [f"car-{i}" for i in range(1, 301)]


def test_same_owner_from_same_membership_in_any_order_and_process():
    members = ["dmc-1", "dmc-2", "dmc-3"]
    a = groups.assignment(CARS, members)
    shuffled = members[:]
    random.Random(4).shuffle(shuffled)
    assert groups.assignment(CARS, shuffled) == a
    # another process (another hash salt) computes the very same owners
    code = ("from magmesh import groups; import json; "
            "print(json.dumps(groups.assignment([f'car-{i}' for i in range(1, 301)], ['dmc-3', 'dmc-1', 'dmc-2'])))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    import json

    assert json.loads(out) == a
    assert set(a.values()) == set(members)


def test_every_vehicle_has_exactly_one_owner_and_none_without_members():
    a = groups.assignment(CARS, ["x-1", "x-2"])
    assert set(a) == set(CARS)
    assert all(o in ("x-1", "x-2") for o in a.values())
    assert groups.owner("car-1", []) is None
    per = groups.by_member(a, ["x-1", "x-2", "x-3"])
    assert per["x-3"] == []
    assert sorted(per["x-1"] + per["x-2"]) == sorted(CARS)


def test_balance():
    for n in (2, 3, 4, 5):
        members = [f"dmc-{k}" for k in range(1, n + 1)]
        fleet = [f"car-{i}" for i in range(3000)]
        counts = [len(v) for v in groups.by_member(groups.assignment(fleet, members), members).values()]
        fair = len(fleet) / n
        # 3000 vehicles: each member within ±15 % of its fair share (the binomial spread is 3-5 %)
        assert min(counts) > 0.85 * fair and max(counts) < 1.15 * fair, counts


def test_join_moves_only_to_the_new_member_about_one_nth():
    before = groups.assignment(CARS, ["dmc-1", "dmc-2", "dmc-3"])
    after = groups.assignment(CARS, ["dmc-1", "dmc-2", "dmc-3", "dmc-4"])
    mv = groups.moved(before, after)
    assert mv, "a new member takes some vehicles"
    assert all(new == "dmc-4" for _, new in mv.values())
    assert 0.15 * len(CARS) < len(mv) < 0.35 * len(CARS)


def test_leave_moves_only_the_leavers_vehicles():
    before = groups.assignment(CARS, ["dmc-1", "dmc-2", "dmc-3"])
    after = groups.assignment(CARS, ["dmc-1", "dmc-3"])
    mv = groups.moved(before, after)
    assert set(mv) == {v for v, o in before.items() if o == "dmc-2"}
    assert all(old == "dmc-2" and new in ("dmc-1", "dmc-3") for old, new in mv.values())


def test_moved_lists_nothing_for_equal_assignments():
    a = groups.assignment(CARS[:10], ["a-1"])
    assert groups.moved(a, dict(a)) == {}


def test_stages_with_as_many_members_give_each_vehicle_to_the_members_of_the_same_number():
    """Co-partitioned stages: a vehicle's owner in one group has the number of its owner in any other group of as
    many members (ingest-2's frames carry exactly what dmc-2 holds), and nearly so with one member more."""
    a = groups.assignment(CARS, ["ingest-1", "ingest-2"])
    b = groups.assignment(CARS, ["dmc-2", "dmc-1"])
    assert {v: groups.slot(o) for v, o in a.items()} == {v: groups.slot(o) for v, o in b.items()}
    c = groups.assignment(CARS, ["heading-1", "heading-2", "heading-3"])
    same = sum(groups.slot(c[v]) == groups.slot(a[v]) for v in CARS if groups.slot(c[v]) != "3")
    assert same == sum(1 for v in CARS if groups.slot(c[v]) != "3")  # those not on the third member stay aligned
    assert groups.slot("dmc-12") == "12" and groups.slot("dmc") == "dmc" and groups.slot("-3") == "-3"
