"""A test service that raises and clears one alarm per vehicle at a fixed period, through the real runtime.

Used by mesh tests that need a known stream of alarm transitions (e.g. across hosts while a link goes down):
its status reports how many transitions it published, so a subscriber can prove it lost none.

    python tests/alarm_toggler.py --connect ENDPOINT --set vehicle=car-1 --set period_s=0.8 --set count=20
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from magmesh.runtime import Service, main  # noqa: E402


@dataclass(frozen=True)
class Settings:
    vehicle: str = "car-1"
    source: str = "toggle"
    period_s: float = 0.8  # one transition per period
    count: int = 20  # transitions to publish, then stay quiet
    tick_s: float = 0.05


class AlarmToggler(Service):
    role = "alarm_toggler"
    impl = "toggler"
    Settings = Settings

    def on_start(self) -> None:
        self.transitions = 0
        self.next_t = time.monotonic() + self.settings.period_s

    def on_tick(self) -> None:
        s = self.settings
        if self.transitions >= s.count or time.monotonic() < self.next_t:
            return
        self.next_t += s.period_s
        state = "raised" if self.transitions % 2 == 0 else "cleared"
        self.alarm(s.vehicle, s.source, state, "warning", f"transition {self.transitions}", float(self.transitions),
                   0.5, time.time())
        self.transitions += 1

    def status_extra(self) -> dict:
        return {"transitions": self.transitions}


if __name__ == "__main__":
    main(AlarmToggler)
