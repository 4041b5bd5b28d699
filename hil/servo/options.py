"""The options of a servo run: everything ``hil servo run`` can set, as one frozen dataclass
(:func:`hil.servo.settings.resolve_servo` resolves them with the configuration)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from hil.controllers.servo.model import SAMPLE_PERIOD_S
from hil.core.params import read_params_file
from hil.core.plugins import controller_label
from hil.core.ranges import MAX_MPC_HORIZON, check_at_most, check_duration, check_milliamps
from hil.core.recording.recording_options import RecordingOptions
from hil.core.settings import given_options
from hil.core.verdict import Limit
from hil.errors import UsageError
from hil.servo.defaults import DEFAULT_REFERENCE
from hil.servo.task import PREDICTION_EVERY_REALTIME, PREDICTION_EVERY_TICK_UP_TO_S

CONTROLLER_FORMS = ("mpc, empc, pid, setpoint, FILE.py:Class, package.module:Class or a registered "
                    "name")
#: ``hil servo run``'s flags (argparse dests) -> the option they set, where the names differ
FLAG_OPTIONS = {"duration": "duration_s", "config": "drive_config", "settle": "settle_s",
                "limit": "limits", "param": "params", "params": "params_file",
                "controller_budget": "controller_budget_s"}


@dataclass(frozen=True)
class ServoRunOptions:
    """Everything a servo run is made of (the flags of ``hil servo run``).

    None means "as configured": ``drive`` (drive.toml's ``[bus]``), ``node``
    (``master.node_id``), ``umax`` (``master.current_limit_mA``), ``eds`` (``master.eds``).
    ``drive_config`` is a drive TOML laid over ``hil/configs/drive.toml``; ``safety`` sets keys
    of its ``[safety]`` (``--safety``); ``drive_overrides`` is laid over the result last, for
    tests and scripts. :func:`hil.servo.settings.resolve_servo` resolves them.
    ``prediction_every`` None means every tick in lockstep, ``PREDICTION_EVERY_REALTIME`` ticks
    in real time.
    """

    controller: str | Callable[..., Any]
    params: Mapping[str, Any] = field(default_factory=dict)
    params_file: str | None = None   # --params F.toml: laid under params (the --param flags)
    drive: str | None = None         # a drive URL; None: drive.toml's [bus]
    node: int | None = None          # None: [master] node_id
    ert: str = "foh"
    ht: int = 8
    hu: int = 8
    hp: int = 50
    umax: float | None = None        # mA; None: [master] current_limit_mA
    reference: str = DEFAULT_REFERENCE
    duration_s: float = 2.0
    realtime: bool = False
    out: str | None = None
    drive_config: str | None = None
    settle_s: float = 0.0
    prediction_every: int | None = None
    safety: Mapping[str, Any] = field(default_factory=dict)  # [safety] keys (--safety)
    drive_overrides: Mapping[str, Any] = field(default_factory=dict)
    limits: tuple[Limit, ...] = ()
    controller_budget_s: float | None = None  # per step; None: STEP_BUDGET_S in real time
    recording: RecordingOptions = field(default_factory=RecordingOptions)
    quiet: bool = False              # no progress line on the terminal
    can_log: str | None = None       # every CAN frame to this file (python-can's formats)
    reset_fault: bool = False        # clear a drive FAULT (CiA 402 fault reset) before enabling
    axes: str | None = None          # NAME=NODE,...: several axes (else drive.toml's [[axis]])
    from_here: bool = False          # the reference relative to the position the run starts at
    home: bool = False               # home the axis first (HM); the reference absolute from home
    eds: str | None = None           # the drive's EDS (else drive.toml's [master] eds)
    allow_higher_current: bool = False  # --umax may exceed [master] current_limit_mA (logged)
    allow_looser_safety: bool = False   # --safety may loosen [safety] (logged)
    lab: Mapping[str, Any] | None = None  # the labgrid place of --place (hil.lab.place)

    def __post_init__(self) -> None:
        if self.params_file is not None:  # the file under the --param flags
            object.__setattr__(self, "params", {**read_params_file(self.params_file),
                                                **self.params})
        if self.umax is not None:
            check_milliamps(self.umax, "--umax")
        check_duration(self.duration_s, "--duration", SAMPLE_PERIOD_S)
        for flag, horizon in (("--ht", self.ht), ("--hu", self.hu), ("--hp", self.hp)):
            check_at_most(horizon, MAX_MPC_HORIZON, flag, "the MPC's matrices grow with the "
                          "horizon (a step would take far longer than a 500 us period)")
        if not 0 <= self.settle_s < self.duration_s:
            raise UsageError(f"--settle ({self.settle_s:g} s) must be >= 0 and shorter than "
                             f"--duration ({self.duration_s:g} s)")
        if self.prediction_every is not None and self.prediction_every < 1:
            raise UsageError(f"--prediction-every must be >= 1, got {self.prediction_every}")
        if self.home and self.from_here:
            raise UsageError("--home places the reference absolute from home, --from-here "
                             "where the axis stands: give one")
        if self.node is not None and not 1 <= self.node <= 127:
            raise UsageError(f"--node must be a CANopen node id 1..127, got {self.node}")

    @classmethod
    def from_flags(cls, flags: Mapping[str, Any], *, need_controller: bool = True
                   ) -> ServoRunOptions:
        """The options of ``hil servo run``'s flags as a dict (argparse dests; a sweep's swept
        values laid over them); flags that are not run options (``json``, ``junit``...) are
        ignored, and so are flags not given (None). The horizons ``ht`` and ``hu`` default to
        8, to 3 for ``empc`` (the paper's drive)."""
        values = given_options(flags, (f.name for f in fields(cls)), FLAG_OPTIONS)
        if "controller" not in values:
            if need_controller:
                raise UsageError(f"--controller is required: {CONTROLLER_FORMS}")
            values["controller"] = ""
        values["params"] = dict(values.get("params", {}))
        values["limits"] = tuple(values.get("limits", ()))
        values["safety"] = dict(values.get("safety") or {})
        default_horizon = 3 if values.get("controller") == "empc" else 8
        for horizon in ("ht", "hu"):
            values.setdefault(horizon, default_horizon)
        return cls(**values)

    @property
    def prediction_period(self) -> int:
        if self.prediction_every is not None:
            return self.prediction_every
        long_run = self.duration_s > PREDICTION_EVERY_TICK_UP_TO_S
        return PREDICTION_EVERY_REALTIME if self.realtime or long_run else 1

    @property
    def label(self) -> str:
        return controller_label(self.controller)

    def describe_controller(self) -> str:
        if self.controller == "pid":
            return "pid (cascaded P/PI + notch, Table I)"
        if self.controller in ("mpc", "empc"):
            return (f"{self.controller} ({self.ert.upper()}, H_t = {self.ht}, H_u = {self.hu}, "
                    f"H_p = {self.hp})")
        return self.label

    def record(self) -> dict[str, Any]:
        """The options as the session's ``servo`` metadata records them."""
        info = asdict(self)
        for name in ("drive_overrides", "limits", "controller", "params"):
            info.pop(name)
        return info


def flag_of(field: str) -> str:
    """The ``hil servo run`` flag of an option field."""
    flags = {option: flag for flag, option in FLAG_OPTIONS.items()}
    return "--" + flags.get(field, field).replace("_", "-")
