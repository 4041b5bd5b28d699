"""``hil resim RECORDED.mcap``: what would another controller have done in a recorded
experiment? The recorded run's configuration replayed in lockstep on hil's emulator with
another controller (:mod:`hil.servo.resim`, :mod:`hil.bench.resim`), recorded as a new session
with the same topics, rates and session-time grid."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.cli.argtypes import output_file
from hil.cli.output import add_quiet_argument
from hil.cli.verdict import add_param_argument, finish

if TYPE_CHECKING:
    from hil.bench.resim import BenchResim
    from hil.core.run import RunResult
    from hil.servo.resim import ServoResim

    Resim = ServoResim | BenchResim


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "resim", help="re-run a recorded session with another controller, on the emulator",
        description="Re-simulate a recorded servo or bench session (RECORDED.mcap) with "
        "another controller: its recorded configuration (reference or machining sequence, "
        "disturbance, the emulator's fault schedule, cycle period, axes, current and safety "
        "limits, duration, limits) run again in lockstep on hil's emulator, only the "
        "controller (and its parameters) replaced, and the plant with --model. The new "
        "session has the recording's topics and rates on the same session-time grid, for "
        "'hil compare', and metadata 'resim' naming the recording. A recording of hardware "
        "is re-simulated against the emulator built from its recorded config (or --model); "
        "the first line says which. Exit status as 'hil servo run' / 'hil bench run': 0 "
        "completed, 1 a recorded limit violated, 2 the recording cannot be re-simulated (no "
        "configuration recorded, a controller that cannot be loaded) or the run was stopped, "
        "3 completed with faults.")
    p.add_argument("recorded", metavar="RECORDED.mcap", help="a servo or bench session")
    p.add_argument("--controller", metavar="SPEC",
                   help="the controller: a built-in name, FILE.py:Class, package.module:Class "
                   "or a registered name (default: the recorded one)")
    add_param_argument(p, "laid over the recorded run's parameters when --controller is "
                       "the recorded one (else over none)")
    p.add_argument("--model", metavar="F.json", action="append", default=[],
                   help="servo: the emulator's axis as a model file of 'hil identify' "
                   "([emulator] model); bench: LOAD=F.json, a load of [plant.loads] made that "
                   "model file, once per load (default: the recorded emulator)")
    p.add_argument("--out", metavar="F.mcap", type=output_file,
                   help="the new session (default: RECORDED.resim.mcap beside it)")
    p.add_argument("--json", action="store_true",
                   help="print the run's KPIs as JSON, with 'resim' (of, controller, params, "
                   "plant, recorded_on)")
    add_quiet_argument(p)
    p.set_defaults(handler=resim_command, junit=None)


def resim_command(args: argparse.Namespace) -> int:
    from hil.bench import resim as bench_resim
    from hil.core.recording.reader import read_session
    from hil.core.resim import read_recorded
    from hil.errors import UsageError
    from hil.servo import resim as servo_resim

    if not os.path.exists(args.recorded):
        raise UsageError(f"{args.recorded}: no such session file")
    data = read_session(args.recorded)
    recorded = read_recorded(data, (*servo_resim.KINDS, *bench_resim.KINDS))
    out = args.out or str(Path(args.recorded).with_suffix(".resim.mcap"))
    if os.path.abspath(out) == os.path.abspath(args.recorded):
        raise UsageError(f"--out {out} is the recording itself; choose another file")
    params = dict(args.param)
    with tempfile.TemporaryDirectory(prefix="hil-resim-") as folder:
        if recorded.kind in bench_resim.KINDS:
            bench = bench_resim.plan_resim(recorded, args.controller, params, args.model, out,
                                           folder, quiet=args.quiet)
            return finish(args, "hil resim", lambda: bench,
                          lambda r: _with_resim(args, r, bench_resim.run_resim(r, args.recorded)),
                          _bench_summary(args))
        if len(args.model) > 1:
            raise UsageError(f"--model given {len(args.model)} times: a servo session takes one "
                             "axis model file")
        drive = data.metadata.get("drive", {}).get("json")
        servo = servo_resim.plan_resim(recorded, args.controller, params,
                                       args.model[0] if args.model else None, out, folder,
                                       _json(drive), quiet=args.quiet)
        return finish(args, "hil resim", lambda: servo,
                      lambda r: _with_resim(args, r, servo_resim.run_resim(r, args.recorded)),
                      _servo_summary(args))


def _json(text: str | None) -> dict[str, Any] | None:
    import json

    try:
        value = json.loads(text) if text else None
    except json.JSONDecodeError:
        return None
    return value if isinstance(value, dict) else None


def _with_resim(args: argparse.Namespace, resim: Resim, result: RunResult) -> RunResult:
    """The run's KPIs with what it re-simulated (``resim``), for ``--json``."""
    result.kpis["resim"] = {"of": args.recorded, "controller": result.kpis.get("controller"),
                            "params": dict(resim.options.params), "plant": resim.plant,
                            "recorded_on": resim.recorded_url}
    return result


def headline(args: argparse.Namespace, resim: Resim) -> str:
    """The first line: what is re-simulated, with which controller, against which plant."""
    on = (f"hardware at {resim.recorded_url}" if resim.of_hardware else "hil's emulator")
    return (f"resim of {args.recorded} (recorded on {on}): controller "
            f"{resim.options.controller} against {resim.plant}")


def _servo_summary(args: argparse.Namespace) -> Any:
    from hil.cli.servo import format_axes_run, format_run

    def summary(resim: ServoResim, kpis: dict[str, Any]) -> str:
        body = (format_axes_run if "axes" in kpis else format_run)(resim.options, kpis)
        return f"{headline(args, resim)}\n{body}"
    return summary


def _bench_summary(args: argparse.Namespace) -> Any:
    from hil.cli.bench import format_kpis

    def summary(resim: BenchResim, kpis: dict[str, Any]) -> str:
        rest = {key: value for key, value in kpis.items() if key != "resim"}  # the headline's
        return f"{headline(args, resim)}\n{format_kpis(rest)}"
    return summary
