"""The alarm latch: an alarm's raised/cleared state with hysteresis, the one rule every service's alarms follow.

An alarm is raised once its raise condition has held for ``raise_after_s`` without interruption and cleared once
its clear condition has held for ``clear_after_s``. The two conditions are separate (a value above the raise level
raises, one below a lower clear level clears; in between nothing changes), so a value near its threshold cannot
make the alarm flap. Uses:

- the DMC detector: raise on invalid epochs for ``raise_after_s``, clear on valid ones for ``clear_after_s``
  (``services.dmc_detector.core.AlarmLatch``; its fleet kernel is the same rule compiled, tested against it);
- the track monitor: alarm/track (d above the threshold on trusted GNSS for ``track_persist_s``; back below the
  clear level for ``clear_hold_s``), alarm/heading_innovation and alarm/mag_anomaly (at once; quiet for the hold);
- the geomagnetic matcher: alarm/match (at once above ``divergence_alarm_m``, at once below 0.8 × it);
- the heading fuser: alarm/heading (at once while the heading is uncertain; at once when magnetic again or its σ
  is below the clear level), the rule its compiled join applies (held to this class by the heading frame tests).

A time counts as having held a hold when it is within ``slack_s`` of it (the DMC's 1 ns; the track monitor's
holds are exact). Pure Python; no zenoh.
"""

from __future__ import annotations


class AlarmLatch:
    """Raised/cleared with hysteresis. :meth:`update` per sample returns ``"raised"``, ``"cleared"`` or None.

    ``valid``: the clear condition holds at this sample; ``invalid``: the raise condition holds (default: not
    ``valid``). The time since each condition started is kept across transitions, as is ``raised_t_s`` after a
    clear (until the next raise)."""

    __slots__ = ("raise_after_s", "clear_after_s", "slack_s", "raised", "raised_t_s", "_invalid_since",
                 "_valid_since")

    def __init__(self, raise_after_s: float = 0.0, clear_after_s: float = 0.0, slack_s: float = 1e-9):
        if not (raise_after_s >= 0 and clear_after_s >= 0):
            raise ValueError("raise_after_s and clear_after_s must be ≥ 0")
        self.raise_after_s, self.clear_after_s, self.slack_s = float(raise_after_s), float(clear_after_s), slack_s
        self.reset()

    def reset(self) -> None:
        self.raised = False
        self.raised_t_s: float | None = None
        self._invalid_since: float | None = None
        self._valid_since: float | None = None

    def update(self, t_s: float, valid: bool, invalid: bool | None = None) -> str | None:
        if invalid is None:
            invalid = not valid
        if valid:
            if self._valid_since is None:
                self._valid_since = t_s
        else:
            self._valid_since = None
        if invalid:
            if self._invalid_since is None:
                self._invalid_since = t_s
        else:
            self._invalid_since = None
        if self.raised:
            if valid and t_s - self._valid_since >= self.clear_after_s - self.slack_s:
                self.raised = False
                return "cleared"
        elif invalid and t_s - self._invalid_since >= self.raise_after_s - self.slack_s:
            self.raised = True
            self.raised_t_s = t_s
            return "raised"
        return None

    def adopt(self, raised: bool, raised_t_s: float | None = None) -> None:
        """Take over an alarm state decided elsewhere (a restart, a live swap, a hand-over): the run timers are
        kept, so a condition that has already held its hold changes the state at the next sample."""
        self.raised = bool(raised)
        self.raised_t_s = raised_t_s if raised else None

    def state(self) -> dict:
        return {"raised": self.raised, "raised_t_s": self.raised_t_s, "invalid_since": self._invalid_since,
                "valid_since": self._valid_since}
