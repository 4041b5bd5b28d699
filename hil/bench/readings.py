"""Screens on the bench's sensor readings: values no sensor can give, sensors frozen.

* :class:`BadReadings` - a non-finite reading is a fault: dropped, counted, one event per
  episode.
* :class:`StaleReadings` - the meter's registers or a level that should move unchanged for
  :data:`STALE_POLLS` polls in a row: one event per episode.
"""

from __future__ import annotations

import math
from typing import Any

from hil.contracts import EventSink, no_event

#: polls in a row with a frozen reading before it is reported (0.5 s at 100 Hz)
STALE_POLLS = 50


class BadReadings:
    """Readings no sensor can give: a non-finite value (NaN, inf: a float32 register holding
    garbage). Such a reading is a fault: dropped like a failed poll (never published, never
    in the KPIs; the controller keeps the last good one), counted in ``readings``, one
    ``meter.bad_reading`` / ``levels.bad_reading`` event (error) per episode."""

    def __init__(self, on_event: EventSink = no_event) -> None:
        self.on_event = on_event
        self.readings = 0
        self.episodes = 0
        self._bad: dict[str, bool] = {}

    def screen(self, device: str, values: dict[str, float], t_ns: int
               ) -> dict[str, float] | None:
        """``values``, or None when one of them is not finite."""
        bad = {name: value for name, value in values.items() if not math.isfinite(value)}
        was_bad = self._bad.get(device, False)
        self._bad[device] = bool(bad)
        if not bad:
            return values
        self.readings += 1
        if not was_bad:
            self.episodes += 1
            self.on_event(f"{device}.bad_reading", f"{device} reading not finite "
                          f"({', '.join(f'{k} = {v}' for k, v in bad.items())}): dropped "
                          "until the readings are finite again", level="error", source="bench",
                          values={k: str(v) for k, v in bad.items()})
        return None


class StaleReadings:
    """Frozen sensors: the meter's registers bit-identical for ``polls`` polls in a row (its
    noise never repeats), or a level unchanged that long while its consumer or supplier
    relay is on (a known non-zero rate). One event per episode (``meter.stale``,
    ``levels.stale``, error); ``episodes`` counts them."""

    def __init__(self, polls: int, rates: dict[str, tuple[str, float, str, float]],
                 on_event: EventSink = no_event) -> None:
        self.polls, self.rates, self.on_event = polls, rates, on_event
        self.episodes = 0
        self._last: dict[str, Any] = {}
        self._runs: dict[str, int] = {}

    def check(self, power: dict[str, float] | None, levels: dict[str, float] | None,
              relays: dict[str, bool], t_ns: int) -> None:
        if power is not None:
            self._same("meter", tuple(power.values()), True, t_ns)
        if levels is not None:
            for name, value in levels.items():
                consumer, alpha, supplier, eta = self.rates.get(name, ("", 0.0, "", 0.0))
                rate = alpha * relays.get(consumer, False) + eta * relays.get(supplier, False)
                self._same(f"levels.{name}", value, rate != 0, t_ns)

    def _same(self, key: str, value: Any, should_move: bool, t_ns: int) -> None:
        same = should_move and self._last.get(key) == value
        self._last[key] = value
        run = self._runs[key] = self._runs.get(key, 0) + 1 if same else 0
        if run == self.polls:
            self.episodes += 1
            device = key.split(".")[0]
            self.on_event(f"{device}.stale", f"{key} unchanged for {self.polls + 1} polls: "
                          "the sensor looks frozen", level="error", source="bench",
                          reading=key)
