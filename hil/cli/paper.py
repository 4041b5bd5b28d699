"""``hil paper NAME``: a paper's tables and figures reproduced from lockstep runs on the
emulators, the paper's value beside hil's in every cell (:mod:`hil.paper`).

A paper is one entry of :data:`PAPERS`: the module whose ``reproduce(options)`` makes its
report, and the words of its ``--help``.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from dataclasses import dataclass
from pathlib import Path

from hil.cli.output import json_text
from hil.errors import UsageError


@dataclass(frozen=True)
class Paper:
    """A reproducible paper: ``module`` has ``reproduce(PaperOptions) -> PaperReport``."""

    module: str
    help: str
    description: str


PAPERS: dict[str, Paper] = {
    "energy": Paper(
        "hil.paper.energy",
        "the energy paper: EEC against BC on the relay bench (Tables I-IV, Figs. 3-6)",
        "Reproduce Diaz C. and Ocampo-Martinez, 'Energy efficiency improvement of machine "
        "tools via peripheral devices management: an optimization-based control approach': "
        "every table and figure from lockstep runs on the emulated bench under the paper's "
        "conditions (hil/configs/paper_energy.toml), the paper's value beside hil's with the "
        "ratio, and a sensitivity sweep of the energy gain J1 that explains the differences."),
    "servo": Paper(
        "hil.paper.servo",
        "the servo paper: MPC (FOH/ZOH, H_t), explicit MPC and PID on the drive (Figs. 1-16)",
        "Reproduce Stephens, Manzie and Good, 'Model Predictive Control for Reference Tracking "
        "on an Industrial Machine Tool Servo Drive': the MPC variants' errors against the "
        "trajectory horizon, the explicit MPC's regions, controllers and search tree and its "
        "evaluation time against the online QP, the cascaded PID + notch baseline, and the "
        "tracking, error and waterfall plots, from lockstep runs on the emulated drive under "
        "the paper's conditions (hil/configs/paper_servo.toml), the paper's value beside hil's "
        "with the ratio, and the sweeps that explain the differences."),
}


def register(subparsers: argparse._SubParsersAction) -> None:
    paper = subparsers.add_parser(
        "paper", help="reproduce a paper's tables and figures, hil's value beside each",
        description="Run a paper's experiments in lockstep on hil's emulators and write its "
        "report: NAME.md (figures in NAME/), NAME.html (one page that opens offline) and "
        "NAME.json in --out; the sessions behind it in NAME/sessions/. Exit 0 when every "
        "table and figure of the paper is in the report, 1 when one is missing (named).")
    papers = paper.add_subparsers(dest="paper", metavar="PAPER", required=True)
    for name, entry in PAPERS.items():
        parser = papers.add_parser(name, help=entry.help, description=entry.description)
        parser.add_argument("--quick", action="store_true",
                            help="a shortened set of runs (seconds, not minutes): every table "
                            "and figure, figures not worth quoting")
        parser.add_argument("--out", metavar="DIR", default="papers",
                            help="folder of the report (default: papers)")
        parser.add_argument("--json", action="store_true",
                            help="print where the report is and what it holds as JSON")
        parser.set_defaults(handler=paper_command)


def paper_command(args: argparse.Namespace) -> int:
    """Reproduce ``args.paper``; exit 1 when its report lacks a table or figure."""
    from hil.paper.report import PaperOptions, write_report

    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"--out {out}: cannot create the folder: {exc.strerror}") from None
    options = PaperOptions(args.paper, quick=args.quick, out=out)
    report = importlib.import_module(PAPERS[args.paper].module).reproduce(options)
    files = write_report(report, out)
    missing = report.missing()
    summary = {"paper": args.paper, "quick": args.quick, "wall_s": round(report.wall_s, 1),
               "markdown": str(files.markdown), "html": str(files.html),
               "json": str(files.json), "items": report.items(), "missing": missing}
    if args.json:
        print(json_text(summary))
    else:
        print(f"{report.title}\n  report  {files.markdown} (and {files.html.name}, "
              f"{files.json.name})\n  holds   {', '.join(report.items())}\n  took    "
              f"{report.wall_s:.0f} s")
    if missing:
        print(f"hil: the report lacks {', '.join(missing)}", file=sys.stderr)
        return 1
    return 0
