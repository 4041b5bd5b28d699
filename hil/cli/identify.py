"""``hil identify``: N4SID model of recorded signals, written to a model file, and what the
model says about the machine (:mod:`hil.controllers.ident.analysis`); ``--servo`` takes a servo
session's signals itself (:func:`hil.servo.identify.servo_signals`)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.cli.argtypes import output_file, positive_int
from hil.controllers.ident.defaults import BLOCK_ROW_CANDIDATES, DEFAULT_MAX_ORDER
from hil.errors import UsageError

if TYPE_CHECKING:
    from hil.controllers.ident.analysis import ModelAnalysis
    from hil.controllers.ident.n4sid import IdentifiedModel


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "identify",
        help="N4SID model from a recorded session",
        description="Identify a discrete-time state-space model (N4SID) from signals recorded in "
        "a session file, report its fit on held-out data (simulated output) and what it says about "
        "the machine (resonances: frequency and damping; integrators; the DC gain, or with "
        "integrators the gain of the integrating part, e.g. a servo axis' rigid-body gain in "
        "deg/s^2 per mA) and write a model "
        "file the controllers' configs can point to. Signals are TOPIC:FIELD, FIELD a path of "
        "keys joined by '.' with list elements as [N], e.g. /bench/power:L2, "
        "/bench/relays:coils[2], /bench/power:phases[1].va.",
    )
    p.add_argument("file", help="session file (.mcap)")
    p.add_argument("--input", action="append", metavar="TOPIC:FIELD", dest="inputs",
                   help="input signal (repeat for several inputs)")
    p.add_argument("--output", action="append", metavar="TOPIC:FIELD", dest="outputs",
                   help="output signal (repeat for several outputs; the first one's time "
                   "stamps are the sampling grid)")
    p.add_argument("--order", type=positive_int,
                   help="model order (default: the BIC-best of the orders the singular "
                   "values allow, up to --max-order)")
    p.add_argument("--max-order", type=positive_int, default=DEFAULT_MAX_ORDER,
                   help=f"highest order tried when --order is not given (default "
                   f"{DEFAULT_MAX_ORDER})")
    p.add_argument("--block-rows", type=positive_int,
                   help="block rows of the Hankel matrices (default: the training-BIC best of "
                   f"{', '.join(map(str, BLOCK_ROW_CANDIDATES))}, raised if the order needs "
                   "more; the model file records the choice)")
    p.add_argument("--train-fraction", type=fraction, default=0.7,
                   help="leading part of the record used for estimation; the fit is "
                   "computed on the rest (default 0.7)")
    p.add_argument("--detrend", action="store_true",
                   help="remove the training means (stored as offsets in the model)")
    p.add_argument("--no-feedthrough", action="store_true", help="force D = 0")
    p.add_argument("--servo", action="store_true",
                   help="a servo session ('hil servo identify', 'hil servo run'): input the "
                   "current commanded on the wire, output the multi-turn position "
                   "(/drive/feedback:command_mA and :position_deg, the command paired with "
                   "the position it starts from: no feedthrough, as the published axis "
                   "model); instead of --input and --output")
    p.add_argument("--axis", metavar="NAME",
                   help="with --servo: the axis NAME of a session with several "
                   "(/axis/NAME/feedback)")
    p.add_argument("--out", metavar="MODEL.json", type=output_file,
                   help="model file (default: next to the session, F.model.json)")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.set_defaults(handler=identify_command)


def fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {text!r}") from None
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {text}")
    return value


def identify_command(args: argparse.Namespace) -> int:
    from hil.controllers.ident.model_file import json_text, model_to_dict
    from hil.controllers.ident.n4sid import IdentificationError, identify
    from hil.core.identify import (
        IRREGULAR_TOLERANCE,
        aligned_signals,
        describe_signals,
        experiment_command,
        parse_signal,
        save_model_file,
    )
    from hil.core.recording.reader import read_session
    from hil.servo.identify import servo_signals

    if args.servo and (args.inputs or args.outputs):
        raise UsageError("--servo names the signals itself: leave out --input and --output")
    if args.axis is not None and not args.servo:
        raise UsageError("--axis NAME picks an axis of a servo session: give --servo too")
    data = read_session(args.file)
    stale = 0
    input_names: tuple[str, ...]
    output_names: tuple[str, ...]
    if args.servo:
        source, target, u, y, dt, irregular, stale = servo_signals(data, args.axis)
        input_names, output_names = (source,), (target,)
    else:
        if not args.inputs or not args.outputs:
            raise UsageError(
                "name the signals with --input TOPIC:FIELD and --output TOPIC:FIELD; "
                + describe_signals(data) + " (a servo session: --servo)"
            )
        inputs = [parse_signal(text) for text in args.inputs]
        outputs = [parse_signal(text) for text in args.outputs]
        u, y, dt, irregular = aligned_signals(data, inputs, outputs)
        input_names = tuple(s.text for s in inputs)
        output_names = tuple(s.text for s in outputs)
    out = args.out or str(Path(args.file).with_suffix(".model.json"))
    if os.path.abspath(out) == os.path.abspath(args.file):
        raise UsageError(f"--out {out} is the session file itself; choose another model file")
    try:
        model = identify(
            u, y, dt,
            inputs=input_names, outputs=output_names,
            order=args.order, max_order=args.max_order, block_rows=args.block_rows,
            train_fraction=args.train_fraction, detrend=args.detrend,
            feedthrough=not (args.no_feedthrough or args.servo),
        )
    except IdentificationError as exc:
        raise UsageError(f"{args.file}: {exc}") from None
    model = dataclasses.replace(model, command=regenerate_command(args, model.block_rows, out),
                                experiment=experiment_command(data))
    save_model_file(out, model)
    analysis = analyse_model(model)
    units = SERVO_UNITS if args.servo else None
    if irregular:
        print(f"hil: warning: {irregular} of {len(y) - 1} sampling intervals of "
              f"{output_names[0]} differ from dt = {dt:g} s by more than "
              f"{IRREGULAR_TOLERANCE:.0%} (dropped or late samples?); the model assumes "
              "uniform sampling", file=sys.stderr)
    if stale:
        print(f"hil: warning: {stale} feedback samples of {len(y) + 1} were stale (the drive's "
              "answer late, its values repeated); the model takes them as measured",
              file=sys.stderr)
    if args.json:
        print(json_text({**model_to_dict(model), "model": out,
                         "irregular_intervals": irregular,
                         "analysis": analysis_json(analysis, units)}))
    else:
        print(format_model(model, out) + "\n" + format_analysis(analysis, units))
    return 0


#: the units of a servo model's signals: output, input
SERVO_UNITS = ("deg", "mA")


def analyse_model(model: IdentifiedModel) -> ModelAnalysis:
    """:func:`~hil.controllers.ident.analysis.analyse` of an identified model (its record:
    every sample it was identified from)."""
    from hil.controllers.ident.analysis import analyse

    record_s = max(model.samples.get("total", 0), 2) * model.dt
    return analyse(model.A, model.B, model.C, model.D, model.dt, record_s)


def gain_unit(integrators: int, units: tuple[str, str] | None) -> str:
    """The unit of the gain of a model with ``integrators`` (``units``: output, input; None:
    the signals' own)."""
    out, per = units or ("output", "input")
    return f"{out}/s^{integrators} per {per}" if integrators else f"{out} per {per}"


def analysis_json(analysis: ModelAnalysis, units: tuple[str, str] | None) -> dict[str, Any]:
    """``--json``'s ``analysis``: the model's resonances, integrators and gain, with the
    gain's unit."""
    return {**analysis.to_dict(), "gain_unit": gain_unit(analysis.integrators, units)}


def format_analysis(analysis: ModelAnalysis, units: tuple[str, str] | None) -> str:
    """The analysis lines of the text report."""
    lines = ["resonances:   " + ("; ".join(
        f"{r.frequency_hz:.2f} Hz, damping {r.damping_ratio:.4f} (peak {r.peak_gain:.3g})"
        for r in analysis.resonances) or "none (no complex pole pair)")]
    unit = gain_unit(analysis.integrators, units)
    if analysis.dc_gain is not None:
        lines.append(f"DC gain:      {_gains(analysis.dc_gain)} {unit}")
        return "\n".join(lines)
    k = analysis.integrators
    name = "rigid-body gain" if units == SERVO_UNITS and k == 2 else f"gain lim s^{k} G(s)"
    lines.append(f"integrators:  {k} (poles slower than {analysis.slowest_hz:.3g} Hz): the DC "
                 f"gain is infinite; {name} {_gains(analysis.integrator_gain)} {unit}")
    return "\n".join(lines)


def _gains(matrix: Any) -> str:
    rows = [" ".join(f"{v:.4g}" for v in row) for row in matrix]
    return rows[0] if len(rows) == 1 and " " not in rows[0] else "[" + "; ".join(rows) + "]"


def regenerate_command(args: argparse.Namespace, block_rows: int, out: str) -> str:
    """The command line that regenerates the model, every choice spelled out."""
    argv = ["hil", "identify", args.file]
    if args.servo:
        argv.append("--servo")
        if args.axis is not None:
            argv += ["--axis", args.axis]
    for spec in args.inputs or ():
        argv += ["--input", spec]
    for spec in args.outputs or ():
        argv += ["--output", spec]
    if args.order is not None:
        argv += ["--order", str(args.order)]
    else:
        argv += ["--max-order", str(args.max_order)]
    argv += ["--block-rows", str(block_rows), "--train-fraction", f"{args.train_fraction:g}"]
    if args.detrend:
        argv.append("--detrend")
    if args.no_feedthrough:
        argv.append("--no-feedthrough")
    argv += ["--out", out]
    return shlex.join(argv)


def format_model(model: IdentifiedModel, out: str) -> str:
    """Human-readable summary: order, fit, singular values, matrices."""
    import numpy as np

    from hil.core.kpi_text import fit_text

    samples = model.samples
    if model.order_selection.get("method") == "bic":
        how = f"selected by BIC over orders 1-{len(model.order_selection.get('bic', {}))}"
    else:
        how = "given"
    tried = model.block_rows_selection.get("bic", {})
    rows_how = f"training BIC best of {', '.join(tried)}" if tried else "given"
    lines = [
        f"model file:   {out}",
        f"inputs:       {', '.join(model.inputs)}",
        f"outputs:      {', '.join(model.outputs)}",
        f"samples:      {samples.get('total')} (train {samples.get('train')}, held-out "
        f"{samples.get('test')}), dt {model.dt:g} s",
        f"block rows:   {model.block_rows} ({rows_how})",
        f"order:        {model.order} ({how})",
        "singular values: " + " ".join(f"{s:.3g}" for s in model.singular_values[:12]),
        f"fit_pct:      {fit_text(model.fit_pct)} on held-out data (simulated output)",
    ]
    if len(model.outputs) > 1:
        lines += [f"  {name}: {fit_text(fit)}"
                  for name, fit in zip(model.outputs, model.fit_pct_per_output, strict=True)]
    with np.printoptions(precision=6, suppress=False, linewidth=100):
        for name in ("A", "B", "C", "D", "K"):
            matrix = np.array2string(getattr(model, name), prefix="    ")
            lines.append(f"{name} = {matrix}")
    if model.experiment:
        lines.append(f"recorded by:     {model.experiment}")
    lines.append(f"regenerate with: {model.command}")
    return "\n".join(lines)
