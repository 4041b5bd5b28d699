"""The ``hil`` command line: parsing, dispatch, and one-line errors."""

from __future__ import annotations

import argparse
import difflib
import functools
import importlib
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from hil import __version__
from hil.errors import HilError, RunInterruptedError

# each command is registered by the module hil.cli.NAME, in this order in `hil --help`
COMMANDS = ("demo", "bench", "servo", "drive", "sweep", "empc", "identify", "emulate", "report",
            "compare", "export", "replay", "resim", "tune", "twin", "layout", "paper", "doctor")


class OneLineParser(argparse.ArgumentParser):
    """argparse with its errors on one line (the command, the problem, where the help is)
    instead of the whole usage block; the subcommands' parsers are of this class too."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``command`` (one of :data:`COMMANDS`) only that command's
    branch, so that a process imports the command modules it runs and not all eighteen."""
    parser = OneLineParser(
        prog="hil",
        description="Hardware-in-the-loop bridge: run model-based controllers in a fixed-rate "
        "loop against a Modbus relay bench or a CiA 402 servo drive (real or emulated) and "
        "record every session to MCAP.",
        epilog="Start with 'hil demo'. Every command has its own --help.",
    )
    parser.add_argument("--version", action="version", version=f"hil {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in (command,) if command in COMMANDS else COMMANDS:
        importlib.import_module(f"hil.cli.{name}").register(subparsers)
    return parser


def command_of(argv: Sequence[str]) -> str | None:
    """The command ``argv`` names first (None for ``--help``, ``--version`` or a typo: those
    need every command's parser)."""
    return argv[0] if argv and argv[0] in COMMANDS else None


@functools.cache
def _shared_parser(command: str | None) -> argparse.ArgumentParser:
    """The parser of ``command`` (None: of every command), built once per process: parsing
    leaves it as it was (its defaults are only read), and building it costs ~10 ms of CPU,
    which every in-process ``main`` call paid."""
    return build_parser(command)


def _leaf_parser(parser: argparse.ArgumentParser, args: argparse.Namespace
                 ) -> argparse.ArgumentParser:
    """The (sub)command parser that ``args`` came through."""
    while True:
        choices = [action for action in parser._actions
                   if isinstance(action, argparse._SubParsersAction)]
        name = getattr(args, choices[0].dest, None) if choices else None
        if name is None:
            return parser
        parser = choices[0].choices[name]


def parse_arguments(parser: argparse.ArgumentParser, argv: Sequence[str] | None
                    ) -> argparse.Namespace:
    """``argv`` parsed; an unknown flag is refused naming the closest flag of its command."""
    args, extras = parser.parse_known_args(argv)
    if extras:
        leaf = _leaf_parser(parser, args)
        flags = [flag for flag in leaf._option_string_actions if flag.startswith("--")]
        hints = []
        for extra in extras:
            close = difflib.get_close_matches(extra.partition("=")[0], flags, n=1)
            if extra.startswith("-") and close:
                hints.append(f"{extra}: did you mean {close[0]}?")
        leaf.error(f"unrecognized arguments: {' '.join(extras)}"
                   + (f" ({'; '.join(hints)})" if hints else ""))
    return args


def main(argv: Sequence[str] | None = None) -> int:
    # numpy's and scipy's BLAS on one thread unless the user says otherwise, set before a
    # command's modules import numpy (the processes hil starts inherit it): OpenBLAS starts a
    # thread per core that spins after each call, and hil's matrices are small, so a second one
    # gains nothing and takes the core the loop, an emulator or the writer needs (0.1 s of CPU
    # per process, a fifth of an MPC run's)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    arguments = sys.argv[1:] if argv is None else list(argv)
    args = parse_arguments(_shared_parser(command_of(arguments)), arguments)
    from hil.core.command_line import set_command_line

    set_command_line(["hil", *arguments])
    try:
        return int(args.handler(args) or 0)
    except RunInterruptedError as exc:
        print(f"hil: {exc}", file=sys.stderr)
        return exc.exit_status
    except HilError as exc:
        print(f"hil: error: {exc}", file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print("hil: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # output piped into e.g. `head`, which stopped reading
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0

