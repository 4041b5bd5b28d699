"""The shared contracts of hil.contracts: the link watchdog and the device lifecycle."""

import pytest

from hil.contracts import Device, LinkWatchdog
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
