"""Live swap of a role's implementation, run by the supervisor.

Protocol (each step a query to the instance's control queryable, handled in its main loop, so it is
ordered with the messages it processes):

1. start the new implementation with ``--standby``: it subscribes, warms its windows on live input and
   publishes nothing;
2. wait until it has seen ``warmup_s`` of sample time of every vehicle the old instance serves;
3. ask the old instance where it is (last input time per vehicle) and choose a cut-over time per
   vehicle a little ahead of it (``lead_s``);
4. ``arm`` the new one (hold outputs at or after the cut) and ``retire`` the old one (publish only
   outputs before the cut, hold the rest);
5. when the old instance has passed the cut for every vehicle, read its last ``seq`` per key and its
   alarm states; ``takeover`` hands them to the new one, which continues the sequence numbers, adopts
   the alarm states (so nothing is raised or cleared twice) and publishes what it held;
6. ``release`` the old one and stop it.

Outputs are split by sample time, so subscribers see every epoch exactly once, with seq continuing.
If the new instance dies or never gets warm, it is stopped and the old one ``resume``s (publishing what
it held): the role is never left without an owner.
"""

from __future__ import annotations

import logging
import signal
import time
from typing import Any

import msgpack

from magmesh import zconf
from schemas import keys

log = logging.getLogger("magmesh_cli.swap")


class SwapError(RuntimeError):
    pass


def _is_id(v: Any) -> bool:
    try:
        keys.check_id(v)
        return True
    except keys.KeyError_:
        return False


class Swapper:
    def __init__(self, sup: Any, warmup_s: float = 3.0, lead_s: float = 0.5, stall_s: float = 3.0):
        self.sup = sup
        self.warmup_s = warmup_s
        self.lead_s = lead_s
        self.stall_s = stall_s

    def _control(self, role: str, instance: str, req: dict, timeout: float = 10.0) -> dict:
        # answered by the instance's own loop, behind its queue: on a loaded machine that takes seconds
        payload = msgpack.packb(req, use_bin_type=True)
        for rep in self.sup.session.get(keys.svc_control(role, instance), payload=payload, timeout=timeout,
                                        priority=zconf.control_priority()):
            if rep.ok is not None:
                res = msgpack.unpackb(rep.ok.payload.to_bytes())
                if not res.get("ok"):
                    raise SwapError(f"{instance} refused {req.get('op')}: {res.get('error')}")
                return res
        raise SwapError(f"{instance} did not answer {req.get('op')} within {timeout:g} s")

    def _role_of(self, ch: Any) -> str | None:
        from .supervisor import implementations

        try:
            impls, _ = implementations(ch.spec.module)
        except (ImportError, ValueError):
            return None
        roles = {c.role for c in impls.values()}
        return roles.pop() if len(roles) == 1 else None

    @staticmethod
    def _describe(inst: str, impl: str, ch: Any) -> str:
        return f"{inst} ({impl}, vehicles {ch.spec.vehicles or '*'})"

    def _candidates(self, role: str) -> list[tuple[str, Any, dict]]:
        """The running instances that hold ``role`` (mode active), with their state reply."""
        found = []
        for inst, ch in list(self.sup.children.items()):
            if not ch.alive or self._role_of(ch) != role:
                continue
            try:
                st = self._control(role, inst, {"op": "state"}, timeout=2.0)
            except SwapError:
                continue
            if st.get("mode") == "active":
                found.append((inst, ch, st))
        return found

    def _choose(self, role: str, impl: str, instance: str | None, vehicles: str | None) -> tuple[str, Any]:
        """Which instance to hand over. With ``instance`` or ``vehicles`` given, the one that matches; else the
        one instance the new implementation can replace: an instance already running ``impl``, or whose
        manifest settings ``impl`` does not know (e.g. the quasi-static detector's ``level``), is not a
        candidate by default. Several candidates: refused with the list."""
        from .supervisor import check_spec, implementations

        try:
            keys.check_id(role, "role")
            keys.check_id(impl, "implementation")
            if vehicles is not None:
                keys.check_pattern(vehicles, "vehicles pattern")
        except keys.KeyError_ as e:
            raise SwapError(str(e)) from None
        roles = sorted({r for ch in list(self.sup.children.values()) if (r := self._role_of(ch))})
        if role not in roles:
            raise SwapError(f"no process of this mesh serves the role {role!r}; roles: {', '.join(roles) or 'none'}")
        deadline = time.monotonic() + 5
        cands = self._candidates(role)
        while not cands and time.monotonic() < deadline:
            time.sleep(0.2)
            cands = self._candidates(role)
        if not cands:
            raise SwapError(f"no running instance holds the role {role!r}")
        listing = ", ".join(self._describe(i, st.get("impl", "?"), ch) for i, ch, st in cands)
        if instance is not None:
            chosen = [c for c in cands if c[0] == instance]
            if not chosen:
                raise SwapError(f"no running instance {instance!r} holds the role {role!r}; instances: {listing}")
        elif vehicles is not None:
            import zenoh

            want = zenoh.KeyExpr(f"{keys.ROOT}/{vehicles}")
            chosen = [c for c in cands if want.intersects(zenoh.KeyExpr(f"{keys.ROOT}/{c[1].spec.vehicles or '*'}"))
                      or any(want.intersects(zenoh.KeyExpr(f"{keys.ROOT}/{v}")) for v in c[2].get("last_in_t", {})
                             if _is_id(v))]
            if not chosen:
                raise SwapError(f"no instance of {role!r} serves vehicles {vehicles!r}; instances: {listing}")
        else:
            chosen = cands
        impls, _ = implementations(chosen[0][1].spec.module)
        if impl not in impls:
            names = ", ".join(f"{ch.spec.name}-{impl}" for _, ch, _ in chosen)
            err = SwapError(f"{names} not started: {role} has no implementation {impl!r}; known: "
                            f"{', '.join(sorted(impls))}")
            err.holder = chosen[0][0] if len(chosen) == 1 else None
            raise err
        why: dict[str, str] = {}
        fit = []
        for inst, ch, st in chosen:
            if st.get("impl") == impl:
                why[inst] = f"already runs {impl}"
                continue
            try:
                check_spec(ch.spec, impl)
            except ValueError as e:
                why[inst] = str(e)
                continue
            fit.append((inst, ch, st))
        explicit = instance is not None or vehicles is not None
        if explicit and len(chosen) == 1 and not fit:
            raise SwapError(f"{chosen[0][0]} cannot be swapped to {impl}: {why[chosen[0][0]]}")
        if len(fit) == 1:
            return fit[0][0], fit[0][1]
        if not fit:
            raise SwapError(f"no instance of {role!r} can be swapped to {impl}: "
                            + "; ".join(f"{i}: {w}" for i, w in why.items()))
        raise SwapError(f"several instances of {role!r} could be swapped to {impl}: "
                        + ", ".join(self._describe(i, st.get("impl", "?"), ch) for i, ch, st in fit)
                        + ". Name one with --instance NAME or --vehicles PATTERN.")

    @staticmethod
    def _last_words(ch: Any) -> str:
        """The end of a failed process's log (its error), for the swap's reply."""
        lines = ch.last_lines(4)
        return " | ".join(lines) + f" (log: {ch.log_path})" if lines else f"its log is empty ({ch.log_path})"

    def swap(self, role: str, impl: str, timeout_s: float = 20.0, instance: str | None = None,
             vehicles: str | None = None) -> dict:
        t0 = time.monotonic()
        try:
            old_inst, old_child = self._choose(role, impl, instance, vehicles)
        except SwapError as e:
            return {"ok": False, "error": str(e), "holder": getattr(e, "holder", None) or instance}
        base = old_child.spec.name
        new_inst = f"{base}-{impl}"
        n = 2
        while new_inst in self.sup.children:
            new_inst = f"{base}-{impl}-{n}"
            n += 1
        self.sup.event(f"swap {role}: starting {impl} as {new_inst} in standby beside {old_inst}")
        spec = old_child.spec
        new_child = self.sup.add_child(spec, impl_override=impl, instance=new_inst, start=False)
        new_child.cmd.append("--standby")
        new_child.supervised = False  # the swap watches it: not restarted (nor reported as restarting) meanwhile
        new_child.start()
        retired = False
        try:
            # 1-2: wait for the new instance to answer and to be warm on every vehicle the old one serves
            old_state = self._control(role, old_inst, {"op": "state"})
            vehicles = set(old_state.get("last_in_t", {}))
            while True:
                if not new_child.alive:
                    raise SwapError(f"{new_inst} exited with code {new_child.proc.returncode} before it was ready: "
                                    f"{self._last_words(new_child)}")
                if time.monotonic() - t0 > timeout_s:
                    raise SwapError(f"{new_inst} was not warm within {timeout_s:g} s")
                try:
                    st = self._control(role, new_inst, {"op": "state"}, timeout=1.0)
                except SwapError:
                    time.sleep(0.2)
                    continue
                if st.get("mode") != "standby":
                    raise SwapError(f"{new_inst} is in mode {st.get('mode')!r}, not standby")
                span = {v: st["last_in_t"].get(v, 0) - st["first_in_t"].get(v, 0) for v in st.get("last_in_t", {})}
                if all(span.get(v, -1) >= self.warmup_s for v in vehicles):
                    break
                time.sleep(0.2)
            # 3-4: agree a cut-over time per vehicle
            old_state = self._control(role, old_inst, {"op": "state"})
            cut = {v: t + self.lead_s for v, t in old_state.get("last_in_t", {}).items()}
            self._control(role, new_inst, {"op": "arm", "cut": cut})
            self._control(role, old_inst, {"op": "retire", "cut": cut})
            retired = True
            # 5: wait for the old one to pass the cut on every vehicle; a vehicle whose input stopped advancing for
            # stall_s counts as done (nothing more will come before the cut). A lagging old instance is waited for.
            hand = None
            progress: dict[str, tuple[float, float]] = {}
            hand_deadline = time.monotonic() + max(timeout_s, 30.0)
            while True:
                if not new_child.alive:
                    raise SwapError(f"{new_inst} exited with code {new_child.proc.returncode} during the hand-over: "
                                    f"{self._last_words(new_child)}")
                if time.monotonic() > hand_deadline:
                    raise SwapError(f"{old_inst} did not reach the cut-over point in time")
                hand = self._control(role, old_inst, {"op": "state"})
                if hand.get("ready"):
                    break
                now = time.monotonic()
                waiting = [v for v in cut if v not in hand.get("passed_cut", [])]
                for v in waiting:
                    t = hand["last_in_t"].get(v)
                    if v not in progress or progress[v][0] != t:
                        progress[v] = (t, now)
                if all(now - progress[v][1] >= self.stall_s for v in waiting):
                    break
                time.sleep(0.05)
            res = self._control(role, new_inst, {"op": "takeover", "seqs": hand["seqs"], "alarms": hand["alarms"],
                                                 "raised": hand.get("raised", {})})
            self._control(role, old_inst, {"op": "release"})
        except Exception as e:
            reason = str(e)
            self.sup.event(f"swap {role} to {impl} failed: {reason}; {old_inst} stays in charge")
            self.sup.remove_child(new_inst, sig=signal.SIGKILL)
            if retired:
                try:
                    self._control(role, old_inst, {"op": "resume"})
                except SwapError as e2:
                    reason += f"; resume failed too: {e2}"
            return {"ok": False, "error": reason, "holder": old_inst}
        # 6: the new one holds the role; a later restart of it must not come back in standby
        new_child.cmd.remove("--standby")
        new_child.supervised = True
        self.sup.remove_child(old_inst)
        took = time.monotonic() - t0
        self.sup.event(f"swap {role}: {new_inst} ({impl}) took over from {old_inst} in {took:.1f} s")
        return {"ok": True, "role": role, "old": old_inst, "new": new_inst, "impl": impl, "cut": cut,
                "seqs": hand["seqs"], "held_published": res.get("held", 0), "took_s": round(took, 2)}
