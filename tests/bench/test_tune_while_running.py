"""Parameters changed while a bench run runs (hil/core/tuning.py): the EEC's horizon and
weights are rebuilt off the loop and used from the next decision; a safety limit may only be
tightened. One lockstep bench cycle, the requests queued before its first tick."""

import threading

import pytest

from hil import api
from hil.core.recording.reader import read_session

pytestmark = [pytest.mark.slow]


def test_the_eec_horizon_changes_at_its_decision_and_a_loosening_is_refused(tmp_path):
    results, specs = [], []

    def tune(tuner):
        specs.extend(tuner.specs())
        asks = [tuner.submit("controller.hp_s", 14, "test", at_tick=2000),
                tuner.submit("controller.gamma2", 0.5, "test", at_tick=2000),
                tuner.submit("controller.hp_s", 2.5, "test"),
                tuner.submit("safety.max_total_va", 2000, "test"),
                tuner.submit("safety.max_total_va", 1100, "test", at_tick=100)]
        waiting = threading.Thread(target=lambda: results.extend(
            tuner.wait(asked, 600.0) for asked in asks))
        waiting.start()

    out = tmp_path / "bench.mcap"
    api.run_bench("eec", cycles=1, out=str(out), quiet=True, tuner_started=tune)
    assert {(s.name, s.unit, s.rebuild, s.stricter) for s in specs} >= {
        ("controller.gamma1", "", True, None), ("controller.hp_s", "s", True, None),
        ("safety.max_total_va", "VA", False, "lower"), ("safety.level_min", "", False,
                                                       "higher")}
    hp, gamma2, fraction, loosened, tightened = results
    # both rebuilds asked for at tick 2000 are in place at it: the second starts from the
    # first's swap, which the loop applies while it waits for the second
    assert (hp.accepted, hp.tick, gamma2.accepted, gamma2.value, gamma2.tick) == \
        (True, 2000, True, 0.5, 2000)
    assert not fraction.accepted and "a whole number [s]" in fraction.reason
    assert not loosened.accepted and "may only be lowered" in loosened.reason
    assert (tightened.accepted, tightened.tick, tightened.value) == (True, 100, 1100.0)
    # the decision at t = 20 s (tick 2000, 10 ms a tick) is the first with the new horizon
    horizons = {round(t_ns / 1e9): len(plan["u"]["P1"])
                for t_ns, plan in read_session(out).topic("/eec/plan")}
    assert {n for t, n in horizons.items() if t < 20} == {28}
    assert {n for t, n in horizons.items() if t >= 20} == {14}
