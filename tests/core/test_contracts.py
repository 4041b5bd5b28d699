"""The shared contracts of hil.contracts: the link watchdog, the poll budget of a wait for a
peer and the device lifecycle."""

import os

import pytest

from hil.contracts import Device, LinkWatchdog, PollBudget, cpu_contended
from hil.errors import ConfigError, HilError


def test_watchdog_declares_the_link_lost_once_after_limit_failures_in_a_row():
    dog = LinkWatchdog(3, "failed polls")
    assert [dog.failure(), dog.failure()] == [False, False] and not dog.lost
    dog.success()                      # the run starts again
    answers = [dog.failure() for _ in range(5)]
    assert answers == [False, False, True, False, False]  # reported exactly once
    assert dog.lost and dog.losses == 1 and dog.run == 5 and dog.longest_run == 5
    assert dog.describe() == "5 failed polls in a row"
    dog.success()
    assert not dog.lost and dog.run == 0 and dog.longest_run == 5
    assert [dog.failure() for _ in range(3)][-1] is True and dog.losses == 2


def test_watchdog_refuses_a_limit_below_one():
    with pytest.raises(ConfigError, match="must be >= 1, got 0"):
        LinkWatchdog(0, "cycles without feedback")


US = 1_000  # ns


def quiet() -> bool:
    """A machine whose CPUs are not contended (this one may be, under the suite)."""
    return False


def test_a_wait_polls_for_its_window_then_blocks():
    budget = PollBudget(500 * US, contended=quiet)
    budget.start(0)
    assert all(budget.polling(t * US) for t in range(0, 500, 5))  # looks 5 us apart
    assert not budget.polling(500 * US)  # the window is over: block
    budget.start(1_000 * US)  # the next wait polls again
    assert budget.polling(1_010 * US)


def test_a_preempted_wait_blocks_and_three_in_a_row_stop_polling_for_a_while():
    budget = PollBudget(500 * US, preempted_ns=200 * US, strikes=3, backoff_ns=100_000 * US,
                        contended=quiet)
    t = 0
    for strike in range(3):
        budget.start(t)
        assert budget.polling(t + 10 * US)
        assert not budget.polling(t + 300 * US)  # 290 us off the CPU: this wait blocks
        assert budget.backoffs == (1 if strike == 2 else 0)
        t += 1_000 * US
    budget.start(t)  # a busy machine: the next waits block from their start...
    assert not budget.polling(t)
    budget.start(t + 100_000 * US)  # ...for backoff_ns
    assert budget.polling(t + 100_010 * US)


def test_a_clean_wait_between_preempted_ones_keeps_the_polling():
    budget = PollBudget(500 * US, preempted_ns=200 * US, strikes=2, contended=quiet)
    for t in range(0, 20_000 * US, 2_000 * US):  # one burst of another process, every other
        budget.start(t)
        assert budget.polling(t + 10 * US)
        if t % (4_000 * US):
            assert not budget.polling(t + 400 * US)
    assert budget.backoffs == 0


def test_a_contended_machine_blocks_each_wait_and_is_asked_again_after_the_backoff():
    busy = [True]
    asked: list[int] = []

    def contended() -> bool:
        asked.append(len(asked))
        return busy[0]

    budget = PollBudget(500 * US, backoff_ns=100_000 * US, contended=contended)
    budget.start(0)
    assert not budget.polling(0)                   # tasks wait for a CPU: no polling
    busy[0] = False
    budget.start(50_000 * US)
    assert not budget.polling(50_010 * US) and len(asked) == 1  # not asked before backoff_ns
    budget.start(100_000 * US)
    assert budget.polling(100_010 * US) and len(asked) == 2     # asked again: quiet, it polls
    budget.start(150_000 * US)
    assert budget.polling(150_010 * US) and len(asked) == 2


@pytest.mark.parametrize(("line", "contended"), [
    ("some avg10=17.82 avg60=56.35 avg300=62.81 total=28467868533", True),
    ("some avg10=4.76 avg60=2.53 avg300=1.00 total=1234", False),
])
def test_the_cpus_pressure_says_whether_the_machine_is_contended(tmp_path, line, contended):
    pressure = tmp_path / "cpu"
    pressure.write_text(f"{line}\nfull avg10=0.00 avg60=0.00 avg300=0.00 total=0\n")
    assert cpu_contended(str(pressure)) is contended


def test_without_pressure_information_the_load_average_says_it(tmp_path):
    cores = len(os.sched_getaffinity(0))
    missing = str(tmp_path / "none")
    assert cpu_contended(missing, load=lambda: (cores + 1.5, 0.0, 0.0))
    assert not cpu_contended(missing, load=lambda: (cores + 0.5, 9.0, 9.0))

    def unknown() -> tuple[float, float, float]:
        raise OSError("no load average")

    assert not cpu_contended(missing, load=unknown)  # neither: as a quiet machine


class Recording(Device):
    """A device that records its lifecycle calls; safe_state may fail like a lost link."""

    def __init__(self, safe_fails: bool = False) -> None:
        self.watchdog = LinkWatchdog(2)
        self.calls: list[str] = []
        self.safe_fails = safe_fails

    @property
    def url(self) -> str:
        return "test://device"

    def open(self) -> None:
        self.calls.append("open")

    def safe_state(self) -> None:
        self.calls.append("safe_state")
        if self.safe_fails:
            raise HilError("link lost")

    def disconnect(self) -> None:
        self.calls.append("disconnect")


def test_device_close_is_safe_state_then_disconnect_even_when_the_link_is_gone():
    with Recording() as device:
        device.open()
        device.configure()
        device.enable()
        assert device.link_up
    assert device.calls == ["open", "safe_state", "disconnect"]
    failing = Recording(safe_fails=True)
    failing.close()                    # a HilError in safe_state must not skip disconnect
    assert failing.calls == ["safe_state", "disconnect"]


def test_device_link_state_follows_its_watchdog():
    device = Recording()
    device.watchdog.failure()
    assert device.link_up
    device.watchdog.failure()
    assert not device.link_up


def test_a_device_must_implement_the_lifecycle():
    class Incomplete(Device):
        pass

    with pytest.raises(TypeError, match="abstract"):
        Incomplete()  # type: ignore[abstract]
