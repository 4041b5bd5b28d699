"""What every benchmark script shares: its ``--quick`` flag (a seconds-long run that checks the
script still works; ``make test`` runs every benchmark this way) and the defaults that flag
picks."""

from __future__ import annotations

import argparse
from collections.abc import Mapping
from typing import Any

QUICK_HELP = ("a seconds-long run that checks the benchmark still works: fewer repeats, shorter "
              "runs, smaller sizes, optional baselines skipped; the same kind of figures, not "
              "worth quoting (tests/test_benchmarks.py runs every benchmark this way)")


def add_quick(parser: argparse.ArgumentParser) -> None:
    """The ``--quick`` flag."""
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)


def fill_defaults(args: argparse.Namespace, defaults: Mapping[str, tuple[Any, Any]]) -> None:
    """Every option of ``defaults`` (name -> (full run's value, --quick's)) that the command
    line left out."""
    for name, (full, quick) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)
