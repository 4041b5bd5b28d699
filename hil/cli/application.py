"""The one contract between ``hil bench run`` / ``hil servo run`` and their application: how
the flags become the run's options, how the settings are listed (``--print-config``), how it
runs and how its KPIs read on the terminal. Each command module builds its
:class:`RunApplication` when it runs (the application's modules load only then)."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Generic, TypeVar

from hil.cli.output import print_settings
from hil.cli.recording import recording_options
from hil.cli.verdict import finish
from hil.core.run import RunResult
from hil.core.settings import Setting

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

Options = TypeVar("Options", bound="DataclassInstance")  # a run's frozen options


@dataclass(frozen=True)
class RunApplication(Generic[Options]):
    """``command`` (``"hil bench run"``): ``from_flags(flags, need_controller=)`` makes its
    options (a frozen dataclass with ``recording``), ``settings(options)`` lists every
    setting the run would use with its origin, ``run(options)`` runs it, ``summary(options,
    kpis)`` is the human summary of its KPIs."""

    command: str
    from_flags: Callable[..., Options]
    settings: Callable[[Options], list[Setting]]
    run: Callable[[Options], RunResult]
    summary: Callable[[Options, dict[str, Any]], str]

    def options(self, args: argparse.Namespace, need_controller: bool = True) -> Options:
        """The options of parsed run flags (``--out`` and the recording flags included)."""
        flags: Mapping[str, Any] = vars(args)
        options = self.from_flags(flags, need_controller=need_controller)
        return replace(options, recording=recording_options(args))

    def print_config(self, args: argparse.Namespace) -> int:
        """``--print-config``: every setting as the run would use it, and its origin; nothing
        is opened."""
        settings = self.settings(self.options(args, need_controller=False))
        return print_settings(self.command, settings, args.json)

    def command_line(self, args: argparse.Namespace) -> int:
        """The run command: ``--print-config``, or the run and its report."""
        if args.print_config:
            return self.print_config(args)
        return finish(args, self.command, lambda: self.options(args), self.run, self.summary)
