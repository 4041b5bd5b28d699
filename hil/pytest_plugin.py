"""pytest fixtures that put a relay bench and a servo drive under your tests: hil's emulators,
each in its own process on a free 127.0.0.1 port, or your hardware with ``--hil-bench URL`` /
``--hil-drive URL``, or a labgrid target's ``HilBench`` / ``HilDrive`` with labgrid's
``--lg-env ENV.yaml`` (:mod:`hil.lab`; the resource's config, node and EDS apply to the runs).
Installed with hil (entry point ``pytest11``): nothing to import.

::

    def test_my_controller_keeps_the_peak_down(hil_bench):
        kpis = hil_bench.run(MyBenchController, {"on_below": 75}, cycles=1)
        assert kpis["J2_VA"] < 650

    def test_my_pd_tracks(hil_drive):
        kpis = hil_drive.run(MyServoController, {"kp": 300}, duration_s=0.5)
        assert kpis["rms_error_deg"] < 0.5

Faults on purpose: ``@pytest.mark.hil_faults("drop@1-2", "weld@0:relay=P1")`` makes the
fixture's emulator play those faults (``KIND@START[-END][:KEY=VALUE,...]``, seconds after it
starts; see docs/FAULTS.md); ``hil_bench.emulator.fault_events()`` lists what it injected.

Each run's session file is kept under the test's ``tmp_path`` and its path is printed when the
test fails; each run's KPIs and session go to the test's properties (``pytest --junitxml``),
named by the session (``servo-1.rms_error_deg``, ``servo-1.mcap``). A hil error that ends a
test (a drive fault, a safety stop...) fails it with its one line, not a traceback
(``--fulltrace`` shows it). After every test the fixture checks that the hardware was left in
its safe state (relays at their safe levels, the drive not in OPERATION ENABLED) and fails the
test if not.

Regression against a baseline: ``hil_baseline.check()`` holds the test's last run against
``baselines/TEST_NAME.mcap`` beside the test file (the run's metadata and KPIs, and its
``/drive/feedback:position_deg`` and ``/drive/command:command_mA``, or the bench's
``/bench/power:total_va`` and levels, at every tick). The first run records that file (a
``BaselineRecorded`` warning says so); ``--hil-update-baselines`` records it again. Later
runs compare as ``hil compare`` does: exact against the emulator (lockstep), within
``tolerances={"NAME": "SPEC"}`` against hardware; a failure shows the table and writes the
comparison's JSON under ``tmp_path``::

    def test_pd_tracks_as_before(hil_drive, hil_baseline):
        hil_drive.run(MyServoController, {"kp": 300}, duration_s=0.5)
        hil_baseline.check(tolerances={"/drive/feedback:position_deg": "tube:0.01,2ms"})

``--hil-html DIR``: an HTML report of every session the fixtures ran and of every baseline
comparison, in ``DIR`` (:mod:`hil.pytest_html`); a failed comparison writes its page under
``tmp_path`` without it too.
"""

from __future__ import annotations

import abc
import contextlib
from collections.abc import Callable, Generator, Iterator, Mapping
from pathlib import Path
from typing import Any, Generic, TypeVar

import pytest

from hil import api
from hil.core.verdict import kpi_properties
from hil.drivers.bench.safe_bench import SafeBench
from hil.drivers.canopen import CanDriveMaster
from hil.emulator_process import EmulatorProcess
from hil.errors import HilError
from hil.protocols.cia402 import OPERATION_ENABLED, state_of
from hil.pytest_baseline import hil_baseline  # noqa: F401  (a fixture of this plugin)
from hil.pytest_html import add_option as add_html_option
from hil.pytest_html import write_session_reports

#: how long the fixtures' own links (``hil_bench.driver``, the safe-state check after a test)
#: wait for an answer from hil's emulator [s]: its process on a busy machine answers late,
#: which is not what a test of a controller tests (a bench keeps its ``[bus] timeout_s``)
EMULATOR_ANSWER_S = 2.0
#: where a run's KPIs go: ``(name, value)`` pairs, a test's ``user_properties``
Record = Callable[[tuple[str, object]], None]
DeviceT = TypeVar("DeviceT")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "hil_faults(*specs): faults the hil_bench / hil_drive "
                            "emulator plays (KIND@START[-END][:KEY=VALUE,...])")


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("hil", "hardware-in-the-loop fixtures (hil_bench, hil_drive)")
    group.addoption("--hil-bench", metavar="URL", default=None,
                    help="run hil_bench tests against this relay bench (modbus-tcp://H:P, "
                    "modbus-rtu:///dev/X) instead of the emulator")
    group.addoption("--hil-drive", metavar="URL", default=None,
                    help="run hil_drive tests against this drive (socketcand://H:P, "
                    "socketcan://can0...) instead of the emulator")
    group.addoption("--hil-update-baselines", action="store_true", default=False,
                    help="hil_baseline records each test's baseline again instead of "
                    "comparing with it")
    add_html_option(group)


class _UnderTest(abc.ABC, Generic[DeviceT]):
    """What the bench and the drive of one test share: where the device is, whether it is
    hil's emulator (and its process), the session files of the runs, and the device opened
    once when a test asks for it (closed by :meth:`close`)."""

    kind = ""  # the session files' stem: bench-1.mcap, servo-1.mcap...

    def __init__(self, url: str, emulated: bool, directory: Path,
                 record: Record) -> None:
        self.url, self.emulated, self.directory = url, emulated, directory
        self.emulator: EmulatorProcess | None = None  # the emulator process, if it is one
        self.defaults: dict[str, Any] = {}  # run options a labgrid resource sets (config...)
        self.sessions: list[str] = []
        self._record = record
        self._stack = contextlib.ExitStack()
        self._opened: DeviceT | None = None

    def _device(self, open_device: Callable[[], contextlib.AbstractContextManager[DeviceT]]
                ) -> DeviceT:
        if self._opened is None:
            self._opened = self._stack.enter_context(open_device())
        return self._opened

    def _run(self, options: dict[str, Any], run: Callable[[], dict[str, Any]]
             ) -> dict[str, Any]:
        """``run()`` into the next session file (``options["out"]`` unless given), its KPIs
        recorded as the test's properties."""
        for name, value in self.defaults.items():
            options.setdefault(name, value)
        options.setdefault("out", str(self.directory /
                                      f"{self.kind}-{len(self.sessions) + 1}.mcap"))
        self.sessions.append(options["out"])
        return run_recorded(self._record, options["out"], run)

    def close(self) -> None:
        self._stack.close()
        self._opened = None

    @abc.abstractmethod
    def left_unsafe(self) -> str | None:
        """Why the device is not in its safe state after the test (None: it is)."""


class BenchUnderTest(_UnderTest[SafeBench]):
    """The relay bench of one test.

    * ``url`` - where it is (``modbus-tcp://127.0.0.1:PORT`` for the emulator);
    * ``run(controller, params=None, cycles=1, **options)`` - ``hil bench run``'s KPIs against
      ``url``. Against the emulator the run is lockstep over the wire (deterministic, faster
      than real time): the emulator's plant starts again from t = 0 and follows the run's
      time; ``realtime=True`` runs it on the wall clock. Against ``--hil-bench`` it follows
      the wall clock (``realtime=False`` asks for lockstep, which only hil's emulator takes);
    * ``driver`` - the bench behind its safety layer, connected, relays at their safe levels,
      on the wall clock (the emulator's own between runs);
    * ``sessions`` - the session files of the runs.
    """

    kind = "bench"

    @property
    def driver(self) -> SafeBench:
        return self._device(lambda: api.open_bench(self.url, self.defaults.get("config_path"),
                                                   timeout_s=self._answer_s()))

    def _answer_s(self) -> float | None:
        """How long the fixture's own link waits for an answer: :data:`EMULATOR_ANSWER_S` from
        hil's emulator, the config's ``[bus] timeout_s`` from a bench (None)."""
        return EMULATOR_ANSWER_S if self.emulated else None

    def run(self, controller: api.Controller, params: Mapping[str, Any] | None = None,
            cycles: int = 1, **options: Any) -> dict[str, Any]:
        realtime = bool(options.pop("realtime", not self.emulated))
        return self._run(options, lambda: api.run_bench(
            controller, params, bench=self.url, cycles=cycles, realtime=realtime, **options))

    def left_unsafe(self) -> str | None:
        unsafe = self.unsafe_relays()
        return (f"relays {', '.join(unsafe)} were left off their safe level at {self.url}"
                if unsafe else None)

    def unsafe_relays(self) -> list[str]:
        """Relays not at their safe level, read straight from the relay module."""
        from hil.bench.config import load_bench_config
        from hil.drivers.bench.modbus import ModbusBenchDriver, ModbusLink, parse_bus_url

        config = load_bench_config(self.defaults.get("config_path"))
        driver = ModbusBenchDriver(ModbusLink(parse_bus_url(self.url),
                                              self._answer_s() or config.bus.timeout_s,
                                              config.bus.attempts), config.map)
        try:
            actual = driver.read_relays()
        finally:
            driver.close()
        return [name for name, spec in config.map.relays.items() if actual[name] != spec.safe]


class DriveUnderTest(_UnderTest[CanDriveMaster]):
    """The servo drive of one test.

    * ``url`` - where it is (``socketcand://127.0.0.1:PORT`` for the emulator);
    * ``run(controller, params=None, reference=..., duration_s=1.0, **options)`` -
      ``hil servo run``'s KPIs (``options``: :class:`hil.servo.run.ServoRunOptions`). Against
      the emulator the run is lockstep over the wire, against ``--hil-drive`` on the wall clock
      (``realtime=`` says otherwise). Each run starts where the axis stands: the drive is
      enabled at its position and the reference is relative to it (``from_here=True``;
      ``from_here=False``: the reference's own angles). A drive in FAULT stays so and the run
      fails; ``reset_fault=True`` clears it (CiA 402 fault reset) before enabling. In the
      config's mode (``drive_config=``, or ``drive_overrides={"master": {"mode": "csp"}}``:
      CSP, CSV and PV take a controller that returns positions or velocities, e.g.
      ``"setpoint"``); ``home=True`` homes the axis first (the reference then absolute from
      home);
    * ``home(**settings)``, ``move(target_deg, **settings)`` - ``hil drive home`` and ``hil
      drive move``'s KPIs (:func:`hil.api.home_drive`, :func:`hil.api.move_drive`);
    * ``master`` - the CiA 402 master, opened and configured (not enabled); it is closed
      before a ``run``, a ``home`` or a ``move`` (one master per bus);
    * ``sessions`` - the session files of the runs.
    """

    kind = "servo"

    @property
    def master(self) -> CanDriveMaster:
        return self._device(lambda: api.open_drive(self.url, self.defaults.get("drive_config")))

    def run(self, controller: api.Controller, params: Mapping[str, Any] | None = None,
            reference: str = "sine:amplitude=2,frequency=1", duration_s: float = 1.0,
            **options: Any) -> dict[str, Any]:
        self.close()
        options.setdefault("realtime", not self.emulated)
        options.setdefault("from_here", not options.get("home", False))
        return self._run(options, lambda: api.run_servo(
            controller, params, drive=self.url, reference=reference, duration_s=duration_s,
            **options))

    def home(self, **settings: Any) -> dict[str, Any]:
        """Home the axis (``hil drive home``): its KPIs."""
        return self._motion("home", lambda: api.home_drive(self.url, **settings), settings)

    def move(self, target_deg: float, **settings: Any) -> dict[str, Any]:
        """A profile position move to ``target_deg`` (``hil drive move``): its KPIs."""
        return self._motion("move", lambda: api.move_drive(target_deg, self.url, **settings),
                            settings)

    def _motion(self, name: str, run: Callable[[], dict[str, Any]],
                settings: dict[str, Any]) -> dict[str, Any]:
        self.close()
        settings.setdefault("realtime", not self.emulated)
        settings.setdefault("out", str(self.directory / f"{name}-{len(self.sessions) + 1}.mcap"))
        return self._run(settings, run)

    def left_unsafe(self) -> str | None:
        state = self.state()
        return f"the drive at {self.url} was left in {state}" if state == OPERATION_ENABLED \
            else None

    def state(self) -> str:
        """The drive's CiA 402 state, read by SDO without changing anything."""
        from hil.servo.config import load_drive_config
        from hil.servo.rig import open_drive

        master = open_drive(self.url, load_drive_config(self.defaults.get("drive_config")))
        try:
            return state_of(master.sdo.read_int(0x6041, 0, "<H"))
        finally:
            master.disconnect()


def run_recorded(record: Record, session: str, run: Callable[[], dict[str, Any]]
                 ) -> dict[str, Any]:
    """``run()``'s KPIs, recorded as properties named by its ``session`` file
    (``servo-1.rms_error_deg``); a HilError that ends the run records the KPIs so far
    (``status``, ``error``) and goes on."""
    try:
        kpis = run()
    except HilError as exc:
        if exc.result is not None:
            _record_kpis(record, session, exc.result.kpis)
        raise
    _record_kpis(record, session, kpis)
    return kpis


def _record_kpis(record: Record, session: str, kpis: dict[str, Any]) -> None:
    for name, value in kpi_properties(kpis, f"{Path(session).stem}.").items():
        record((name, value))


def _lab_device(request: pytest.FixtureRequest, option: str
                ) -> tuple[str, dict[str, Any]] | None:
    """The device of the labgrid environment's target (``--lg-env``; :mod:`hil.lab`) and the
    run options its resource sets; None without one."""
    if not request.config.pluginmanager.hasplugin("labgrid"):
        return None
    from hil.lab.pytest_target import target_device

    return target_device(request, option)


@contextlib.contextmanager
def _emulator_or(request: pytest.FixtureRequest, option: str, start: Any
                 ) -> Iterator[tuple[str, EmulatorProcess | None, dict[str, Any]]]:
    url = request.config.getoption(option)
    flag = "--" + option.replace("_", "-")
    faults = [spec for mark in request.node.iter_markers("hil_faults") for spec in mark.args]
    lab = _lab_device(request, option)
    defaults: dict[str, Any] = {}
    if lab is not None:
        if url is not None:
            pytest.fail(f"{flag} {url} and --lg-env both name the device: give one")
        url, defaults = lab
        flag = "--lg-env"
    if url is not None:
        if faults:
            pytest.fail(f"hil_faults: faults are played by the emulator, not by {flag} {url}")
        yield url, None, defaults
        return
    emulator: EmulatorProcess = start(faults=faults)
    try:
        yield emulator.url, emulator, defaults
    finally:
        emulator.stop()


UnderTest = TypeVar("UnderTest", bound="_UnderTest[Any]")


def _under_test(request: pytest.FixtureRequest, tmp_path: Path, option: str, start: Any,
                make: type[UnderTest]) -> Generator[UnderTest, None, str | None]:
    """The device of a test (``make``): the emulator ``start`` gives, or the ``--OPTION``
    URL; after the test, closed; returns why the test left it unsafe (None: it did not)."""
    with _emulator_or(request, option, start) as (url, emulator, defaults):
        device = make(url, emulator is not None, tmp_path, request.node.user_properties.append)
        device.emulator, device.defaults = emulator, defaults
        try:
            yield device
        finally:
            device.close()
            write_session_reports(request, device.sessions)
        return device.left_unsafe()


@pytest.fixture
def hil_bench(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[BenchUnderTest]:
    """A relay bench for this test: the emulator in its own process, or ``--hil-bench URL``."""
    unsafe = yield from _under_test(request, tmp_path, "hil_bench", api.start_bench_emulator,
                                    BenchUnderTest)
    if unsafe:
        pytest.fail(f"hil_bench: {unsafe}")


@pytest.fixture
def hil_drive(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[DriveUnderTest]:
    """A servo drive for this test: the emulator in its own process, or ``--hil-drive URL``."""
    unsafe = yield from _under_test(request, tmp_path, "hil_drive", api.start_drive_emulator,
                                    DriveUnderTest)
    if unsafe:
        pytest.fail(f"hil_drive: {unsafe}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]
                               ) -> Generator[None, Any, None]:
    """A failed test that uses the fixtures names its session files; a HilError that failed
    it is its one line (without ``--fulltrace``)."""
    outcome = yield
    report = outcome.get_result()
    if not report.failed:
        return
    funcargs = getattr(item, "funcargs", {})
    under_test = [funcargs[name] for name in ("hil_bench", "hil_drive")
                  if isinstance(funcargs.get(name), BenchUnderTest | DriveUnderTest)]
    if not under_test:
        return
    if call.excinfo is not None and call.excinfo.errisinstance(HilError) \
            and not item.config.getoption("fulltrace", False):
        report.longrepr = f"{call.excinfo.typename}: {call.excinfo.value}"
    paths = [path for fixture in under_test for path in fixture.sessions]
    if paths:
        report.sections.append(("hil sessions", "\n".join(paths)))
