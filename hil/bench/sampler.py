"""The bench's sampler: every sample it services the safety layer, polls the meter (and
levels) and screens the readings (read phase), and records ``/bench/power``,
``/bench/levels`` and ``/bench/relays`` (record phase).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from hil.bench.readings import BadReadings, StaleReadings
from hil.contracts import no_event
from hil.core.loop import Task

if TYPE_CHECKING:
    from hil.core.session import Session
    from hil.drivers.bench.safe_bench import SafeBench


def _number_schema(title: str, description: str, names: list[str]) -> dict[str, Any]:
    return {"type": "object", "title": title, "description": description,
            # SDM630 registers are IEEE 754 float32: float32 on the wire loses nothing
            "properties": {name: {"type": "number", "x-cdr": "float32"} for name in names}}


class BenchSampler(Task):
    """Every sample: service the safety layer, poll the meter (and levels), publish.

    A failed poll publishes nothing for that sample and is counted (``missed_power``); the
    latest good values stay in ``latest_power`` / ``latest_levels`` for controllers, this
    sample's in ``fresh_power`` / ``fresh_levels`` (None when it brought none) for the tasks
    that look at each reading once.
    """

    def __init__(self, bench: SafeBench, session: Session | None = None, *,
                 quantities: list[str], levels: list[str], levels_every: int = 1,
                 readback_every: int = 100, divisor: int = 1, name: str = "bench_io",
                 stale: StaleReadings | None = None) -> None:
        super().__init__(name, divisor)
        self.bench = bench
        self.stale = stale
        self.bad = BadReadings(session.event if session is not None else no_event)
        self.levels_every, self.readback_every = levels_every, readback_every
        self.latest_power: dict[str, float] | None = None
        self.latest_levels: dict[str, float] | None = None
        # this sample's good readings (None: failed, bad or not polled this sample)
        self.fresh_power: dict[str, float] | None = None
        self.fresh_levels: dict[str, float] | None = None
        self.samples = self.missed_power = self.missed_levels = 0
        # this sample as read: power, levels, actual and commanded relays, link up
        self._sample: tuple[Any, Any, dict[str, bool], dict[str, bool], bool] | None = None
        self._topics = None
        if session is not None:
            relay_fields = [*bench.relay_names, *(f"{n}_commanded" for n in bench.relay_names)]
            self._topics = (
                session.topic("/bench/power", _number_schema(
                    "hil.BenchPower", "Power meter (SDM630 registers) of the bench", quantities),
                    high_rate=True),
                session.topic("/bench/levels", _number_schema(
                    "hil.BenchLevels", "Resource levels q_j of the bench", levels),
                    high_rate=True),
                session.topic("/bench/relays", {
                    "type": "object", "title": "hil.BenchRelays",
                    "description": "Relay states (1 = on): actual (verified) and commanded "
                                   "(including changes deferred by the dwell); link_up 0/1",
                    "properties": {f: {"type": "integer", "enum": [0, 1], "x-cdr": "uint8"}
                                   for f in [*relay_fields, "link_up"]},
                }, high_rate=True),
            )

    def read(self, t_ns: int) -> None:
        """Service the safety layer, poll the meter (and levels), check for frozen sensors;
        keep the relays' states as they were read, for the record."""
        n = self.samples
        self.samples += 1
        bench = self.bench
        bench.service(t_ns)
        power = bench.read_power()
        levels = bench.read_levels() if n % self.levels_every == 0 else None
        if self.readback_every and n % self.readback_every == 0 and bench.link_up:
            bench.readback(t_ns)
        if power is not None:
            power = self.bad.screen("meter", power, t_ns)
        if levels is not None:
            levels = self.bad.screen("levels", levels, t_ns)
        if power is None:
            self.missed_power += 1
        if levels is None and n % self.levels_every == 0:
            self.missed_levels += 1
        relays = bench.relays()
        if self.stale is not None:
            self.stale.check(power, levels, relays, t_ns)
        self.fresh_power, self.fresh_levels = power, levels
        if power is not None:
            self.latest_power = power
        if levels is not None:
            self.latest_levels = levels
        self._sample = (power, levels, relays, bench.commanded(), bench.link_up)

    def record(self, t_ns: int) -> None:
        """``/bench/power``, ``/bench/levels`` and ``/bench/relays`` of this sample."""
        if self._topics is None or self._sample is None:
            return
        power, levels, actual, commanded, link_up = self._sample
        power_topic, levels_topic, relays_topic = self._topics
        if power is not None:
            power_topic.log(t_ns, power)
        if levels is not None:
            levels_topic.log(t_ns, levels)
        message: dict[str, int] = {name: int(on) for name, on in actual.items()}
        message.update({f"{name}_commanded": int(on) for name, on in commanded.items()})
        message["link_up"] = int(link_up)
        relays_topic.log(t_ns, message)
