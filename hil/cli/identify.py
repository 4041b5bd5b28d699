"""``hil identify``: N4SID model of recorded signals, written to a model file."""

from __future__ import annotations

import argparse
import dataclasses
import os
import shlex
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from hil.cli.argtypes import output_file, positive_int
from hil.controllers.ident.defaults import BLOCK_ROW_CANDIDATES, DEFAULT_MAX_ORDER
from hil.errors import UsageError

if TYPE_CHECKING:
    from hil.controllers.ident.n4sid import IdentifiedModel


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "identify",
        help="N4SID model from a recorded session",
        description="Identify a discrete-time state-space model (N4SID) from signals recorded in "
        "a session file, report its fit on held-out data (simulated output) and write a model "
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

    data = read_session(args.file)
    if not args.inputs or not args.outputs:
        raise UsageError(
            "name the signals with --input TOPIC:FIELD and --output TOPIC:FIELD; "
            + describe_signals(data)
        )
    inputs = [parse_signal(text) for text in args.inputs]
    outputs = [parse_signal(text) for text in args.outputs]
    u, y, dt, irregular = aligned_signals(data, inputs, outputs)
    out = args.out or str(Path(args.file).with_suffix(".model.json"))
    if os.path.abspath(out) == os.path.abspath(args.file):
        raise UsageError(f"--out {out} is the session file itself; choose another model file")
    try:
        model = identify(
            u, y, dt,
            inputs=tuple(s.text for s in inputs), outputs=tuple(s.text for s in outputs),
            order=args.order, max_order=args.max_order, block_rows=args.block_rows,
            train_fraction=args.train_fraction, detrend=args.detrend,
            feedthrough=not args.no_feedthrough,
        )
    except IdentificationError as exc:
        raise UsageError(f"{args.file}: {exc}") from None
    model = dataclasses.replace(model, command=regenerate_command(args, model.block_rows, out),
                                experiment=experiment_command(data))
    save_model_file(out, model)
    if irregular:
        print(f"hil: warning: {irregular} of {len(y) - 1} sampling intervals of "
              f"{outputs[0].text} differ from dt = {dt:g} s by more than "
              f"{IRREGULAR_TOLERANCE:.0%} (dropped or late samples?); the model assumes "
              "uniform sampling", file=sys.stderr)
    if args.json:
        print(json_text({**model_to_dict(model), "model": out,
                         "irregular_intervals": irregular}))
    else:
        print(format_model(model, out))
    return 0


def regenerate_command(args: argparse.Namespace, block_rows: int, out: str) -> str:
    """The command line that regenerates the model, every choice spelled out."""
    argv = ["hil", "identify", args.file]
    for spec in args.inputs:
        argv += ["--input", spec]
    for spec in args.outputs:
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
        f"fit_pct:      {model.fit_pct:.2f} % on held-out data (simulated output)",
    ]
    if len(model.outputs) > 1:
        lines += [f"  {name}: {fit:.2f} %"
                  for name, fit in zip(model.outputs, model.fit_pct_per_output, strict=True)]
    with np.printoptions(precision=6, suppress=False, linewidth=100):
        for name in ("A", "B", "C", "D", "K"):
            matrix = np.array2string(getattr(model, name), prefix="    ")
            lines.append(f"{name} = {matrix}")
    if model.experiment:
        lines.append(f"recorded by:     {model.experiment}")
    lines.append(f"regenerate with: {model.command}")
    return "\n".join(lines)
