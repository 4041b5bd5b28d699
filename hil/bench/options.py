"""The options of a bench run: everything ``hil bench run`` can set, as one frozen dataclass
(:func:`hil.bench.settings.resolve_bench` resolves them with the configuration)."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from hil.core.params import read_params_file
from hil.core.recording.recording_options import RecordingOptions
from hil.core.settings import given_options
from hil.core.verdict import Limit
from hil.errors import UsageError

#: ``hil bench run``'s flags (argparse dests) -> the option they set, where the names differ
FLAG_OPTIONS = {"hp": "hp_s", "hs": "hs_s", "dwell": "dwell_s", "config": "config_path",
                "duration": "duration_s",
                "limit": "limits", "param": "params", "params": "params_file",
                "controller_budget": "controller_budget_s"}


def flag_of(field: str) -> str:
    """The ``hil bench run`` flag of an option field."""
    flags = {option: flag for flag, option in FLAG_OPTIONS.items()}
    return "--" + flags.get(field, field).replace("_", "-")


@dataclass(frozen=True)
class BenchRunOptions:
    """Everything ``hil bench run`` can set (CLI flags); None = the config's value
    (:func:`hil.bench.settings.resolve_bench` resolves them).

    ``controller`` is a spec (``eec``, ``bc``, ``FILE.py:Class``, ``package.module:Class``, a
    name registered in ``hil.controllers``) or a class; ``params`` are laid over the config's
    ``[controller]`` table; ``limits`` are added to its ``[limits]``; ``overrides`` are
    ``[eec]`` keys set by a program (benchmarks, the demo). The run lasts ``cycles`` machine
    cycles, or ``duration_s`` seconds of session time when given (a smoke test in real time
    need not last a 28 s cycle)."""

    controller: str | Callable[..., Any] = "eec"
    params: Mapping[str, Any] = field(default_factory=dict)
    params_file: str | None = None   # --params F.toml: laid under params (the --param flags)
    bench: str | None = None         # a bench URL; None: bench.toml's [bus] url
    cycles: int = 8
    duration_s: float | None = None  # the run's length instead of whole cycles [s]
    hp_s: int | None = None
    hs_s: int | None = None
    gamma1: float | None = None
    gamma2: float | None = None
    terminal: str | None = None
    dwell_s: float | None = None
    disturbance: bool = False
    realtime: bool = False
    out: str | None = None
    config_path: str | None = None
    seed: int | None = None
    limits: tuple[Limit, ...] = ()
    safety: Mapping[str, Any] = field(default_factory=dict)  # [safety] keys for this run
    controller_budget_s: float | None = None  # per decision; None: the step in real time
    overrides: Mapping[str, Any] = field(default_factory=dict)
    recording: RecordingOptions = field(default_factory=RecordingOptions)
    quiet: bool = False              # no progress line on the terminal
    allow_looser_safety: bool = False  # --safety / --dwell may loosen the config's (logged)
    lab: Mapping[str, Any] | None = None  # the labgrid place of --place (hil.lab.place)

    def __post_init__(self) -> None:
        if self.params_file is not None:  # the file under the --param flags
            object.__setattr__(self, "params", {**read_params_file(self.params_file),
                                                **self.params})

    @classmethod
    def from_flags(cls, flags: Mapping[str, Any], *, need_controller: bool = True
                   ) -> BenchRunOptions:
        """The options of ``hil bench run``'s flags as a dict (argparse dests; a sweep's swept
        values laid over them); flags that are not run options (``json``, ``junit``...) are
        ignored, and so are flags not given (None)."""
        values = given_options(flags, (f.name for f in fields(cls)), FLAG_OPTIONS)
        if need_controller and "controller" not in values:
            raise UsageError("--controller is required: eec, bc, FILE.py:Class, "
                             "package.module:Class or a registered name")
        values["params"] = dict(values.get("params", {}))
        values["limits"] = tuple(values.get("limits", ()))
        values["safety"] = dict(values.get("safety") or {})
        return cls(**values)

    def record(self) -> dict[str, Any]:
        """The options as the session's ``run`` metadata records them."""
        info = {f.name: getattr(self, f.name) for f in fields(self)
                if f.name not in ("overrides", "limits", "recording")}
        info["params"] = dict(self.params)
        info["safety"] = dict(self.safety)
        info["recording"] = asdict(self.recording)
        return info
