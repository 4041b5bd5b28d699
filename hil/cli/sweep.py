"""``hil sweep bench|servo``: many lockstep runs over a grid or a random sample of their
options, on Ray (a local one or a cluster), into one folder of sessions and a results table."""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil.cli import bench, servo
from hil.cli.argtypes import positive_int
from hil.cli.output import json_text
from hil.cli.place import add_place_arguments, run_on_place
from hil.errors import UsageError

if TYPE_CHECKING:  # the sweep machinery (Ray, the runs) is imported when a sweep runs
    from hil.sweep.config import SweepTable
    from hil.sweep.engine import Engine
    from hil.sweep.space import Trial

RUN_ARGUMENTS: dict[str, Callable[[argparse.ArgumentParser], None]] = {
    "bench": bench.add_run_arguments, "servo": servo.add_run_arguments}
URL_KEY = {"bench": "bench", "servo": "drive"}   # the run flag naming the device
SWEEP_DESTS = ("grid", "random", "sweep_config", "seed", "out", "workers", "address",
               "resume", "json", "serial", "handler", "command", "sweep_kind", "place",
               "coordinator", "wait")


def register(subparsers: argparse._SubParsersAction) -> None:
    sweep = subparsers.add_parser(
        "sweep", help="many lockstep runs over a grid or random sample of their options, on Ray")
    kinds = sweep.add_subparsers(dest="sweep_kind", metavar="KIND", required=True)
    for kind, what in (("bench", "hil bench run"), ("servo", "hil servo run")):
        parser = kinds.add_parser(
            kind, help=f"sweep the options of '{what}'",
            description=f"Run '{what}' once per point of a parameter space (--grid: the "
            "Cartesian product; --random: seeded uniform samples; or a [sweep] table), each "
            "trial a lockstep experiment in a Ray task of its own, BLAS single-threaded. A "
            "local Ray with one worker per core is started for the sweep unless --address "
            "joins a cluster. Writes one MCAP per trial (named by its parameters), "
            "results.csv and sweep.png into --out; a failing trial is recorded and the "
            "others go on. Exit status 0 when every trial ran and held its limits, 1 "
            "otherwise, 2 on a usage error. Any flag of the run (without '--') or "
            "param.NAME can be swept.")
        RUN_ARGUMENTS[kind](parser)
        add_sweep_arguments(parser)
        add_place_arguments(parser, URL_KEY[kind])
        parser.set_defaults(handler=sweep_command)


def add_sweep_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of the sweep itself."""
    parser.add_argument("--grid", action="append", default=[], metavar="KEY=v1,v2,...",
                        help="values of one key (repeat: the Cartesian product); separate "
                        "with ';' instead when a value holds commas")
    parser.add_argument("--random", nargs="+", metavar=("N", "KEY=lo:hi"),
                        help="N seeded samples, each key uniform in [lo, hi] (integers for "
                        "integer options); combined with every --grid point")
    parser.add_argument("--seed", type=int, help="seed of --random (default 0)")
    parser.add_argument("--sweep-config", metavar="F.toml",
                        help="a [sweep] table: grid, random, workers, address, seed (the "
                        "flags win)")
    parser.add_argument("--out", metavar="DIR",
                        help="folder of the results (default: sweep-KIND-DATE-TIME)")
    parser.add_argument("--workers", type=positive_int,
                        help="trials at once (default: one per core; on a cluster, its CPUs)")
    parser.add_argument("--address", metavar="ADDR",
                        help="join a Ray cluster: auto (this node is part of it) or "
                        "ray://HOST:PORT (Ray client)")
    parser.add_argument("--resume", action="store_true",
                        help="skip the trials whose results are already in --out")
    parser.add_argument("--serial", action="store_true",
                        help="run the trials one after another in this process, no Ray (the "
                        "only way to sweep a real bench or drive)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON")


def sweep_command(args: argparse.Namespace) -> int:
    """The sweep; on ``--place``, every trial on the place's device, the place held for the
    whole sweep (its trials one after another: ``--serial``)."""
    if args.place is not None and not args.serial:
        raise UsageError(f"--place {args.place}: a place's {URL_KEY[args.sweep_kind]} is one "
                         "device; add --serial to run the trials one after another")
    return run_on_place(args, args.sweep_kind, lambda: _sweep(args))


def _sweep(args: argparse.Namespace) -> int:
    from hil.sweep.config import load_sweep_table
    from hil.sweep.engine import Engine, check_address
    from hil.sweep.sweep import Sweep, check_trials, format_sweep, run_sweep

    kind = args.sweep_kind
    table = load_sweep_table(args.sweep_config) if args.sweep_config else None
    trials, keys = space_of(args, kind, table)
    if args.place is not None and URL_KEY[kind] in keys:
        raise UsageError(f"--place {args.place} and a swept {URL_KEY[kind]} both say where "
                         f"the {URL_KEY[kind]} is: give one")
    base = {k: v for k, v in vars(args).items() if k not in SWEEP_DESTS}
    engine = Engine(workers=args.workers or (table.workers if table else None),
                    address=args.address or (table.address if table else None),
                    serial=args.serial)
    if engine.address and not engine.serial:
        check_address(engine.address)
    refuse_parallel_hardware(kind, base, trials, engine)
    _absolute_paths(base)
    out = Path(args.out or time.strftime(f"sweep-{kind}-%Y%m%d-%H%M%S")).absolute()
    if args.resume and not args.out:
        raise UsageError("--resume needs the --out folder of the sweep to resume")
    sweep = Sweep(kind, base, keys, tuple(trials), out, engine, args.resume)
    check_trials(sweep)
    result = run_sweep(sweep)
    print(json_text(result) if args.json
          else format_sweep(result, kind, keys))
    return 0 if all(t["status"] == "ok" for t in result["trials"]) else 1


def space_of(args: argparse.Namespace, kind: str,
             table: SweepTable | None) -> tuple[list[Trial], tuple[str, ...]]:
    """The trials of the ``[sweep]`` table with the flags laid over it, and the swept keys."""
    from hil.sweep.space import Range, Space, expand

    run_parser = argparse.ArgumentParser(add_help=False)
    RUN_ARGUMENTS[kind](run_parser)
    space = Space(run_parser)
    grid: dict[str, list[Any]] = {}
    ranges: list[Range] = []
    count, seed = 0, 0
    if table is not None:
        where = f"{args.sweep_config}: [sweep.grid]"
        for key, values in table.grid.items():
            name = space.canonical(key, where)
            grid[name] = [space.convert(name, _toml_text(v), f"{where} {key}") for v in values]
        ranges = [space.range_entry(f"{key}={_toml_text(lo)}:{_toml_text(hi)}",
                                    f"{args.sweep_config}: [sweep.random]")
                  for key, (lo, hi) in table.ranges.items()]
        count, seed = table.random_trials, table.seed or 0
    grid.update(space.grid_entry(text) for text in args.grid)
    if args.random:
        count = _count(args.random[0])
        if len(args.random) < 2:
            raise UsageError("--random N KEY=lo:hi: give at least one KEY=lo:hi")
        flag_ranges = [space.range_entry(text) for text in args.random[1:]]
        ranges = [r for r in ranges if r.key not in {f.key for f in flag_ranges}] + flag_ranges
    if args.seed is not None:
        seed = args.seed
    keys = tuple(dict.fromkeys([*grid, *(r.key for r in ranges)]))
    if not keys:
        raise UsageError("nothing to sweep: give --grid, --random or a [sweep] table")
    return expand(grid, space.sample(ranges, count, seed) if ranges else []), keys


def refuse_parallel_hardware(kind: str, base: dict[str, Any], trials: list[Trial],
                             engine: Engine) -> None:
    """A real bench or drive is one device: its trials run one after another (--serial)."""
    from hil.core.registry import scheme_of

    key = URL_KEY[kind]
    urls = dict.fromkeys(str(t.params.get(key, base[key]) or _configured_url(kind, base))
                         for t in trials)
    real = [u for u in urls if scheme_of(u) != "emulated"]
    if real and not engine.serial:
        raise UsageError(f"--{key} {real[0]} is not emulated: a real device cannot run trials "
                         "in parallel; add --serial to run them one after another")


def _configured_url(kind: str, base: dict[str, Any]) -> str:
    """The device a run takes when its flags name none: the drive of drive.toml's [bus]."""
    if kind != "servo":
        return "emulated"
    from hil.servo.config import load_drive_config

    return load_drive_config(base.get("config")).bus_url


def _absolute_paths(base: dict[str, Any]) -> None:
    """Files named relative to here, made absolute for workers that start elsewhere."""
    for key in ("config", "params"):
        if base.get(key):
            base[key] = os.path.abspath(base[key])
    controller = str(base.get("controller", ""))
    path, sep, cls = controller.rpartition(":")
    if sep and path.endswith(".py") and os.path.exists(path):
        base["controller"] = f"{os.path.abspath(path)}:{cls}"


def _count(text: str) -> int:
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError as exc:
        raise UsageError(f"--random N: {exc}") from None


def _toml_text(value: Any) -> str:
    """A TOML value as the text a flag would give (true/false for booleans)."""
    return str(value).lower() if isinstance(value, bool) else str(value)
