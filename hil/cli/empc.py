"""``hil empc build``: explicit MPC regions, search tree, C export."""

from __future__ import annotations

import argparse
from pathlib import Path

from hil.cli.argtypes import positive_float, positive_int
from hil.cli.output import json_text
from hil.errors import UsageError

BOX_HELP = ("box of the relative parameters (controllers/servo/empc.py explains them): "
            "comma-separated "
            "NAME=HALF (symmetric) or NAME=LO:HI with NAME one of dx1..dx4 (state increments "
            "per tick), u (previous current, mA), e (r(1|k) - y, deg), dr or dr2..drHt "
            "(reference steps, deg per tick), plus scale=F to multiply the defaults, e.g. "
            "'e=30,dr=1' or 'scale=0.5'. Default: dx1=10,dx2=3,dx3=0.06,dx4=0.06,e=180,dr=3, "
            "u = the current limits")


def register(subparsers: argparse._SubParsersAction) -> None:
    empc = subparsers.add_parser("empc", help="explicit MPC: build regions, tree, C code")
    empc_sub = empc.add_subparsers(dest="empc_command", metavar="COMMAND", required=True)
    build = empc_sub.add_parser(
        "build", help="solve the mpQP and build the search tree",
        description="Solve the servo MPC (published axis model, Q = 1e6, R = 1, |u| <= umax) "
        "as a multiparametric QP over a box of relative parameters, count regions and distinct "
        "controllers (laws of the first move), build the binary search tree over the region "
        "hyperplanes, and optionally write the law as self-contained C99.")
    build.add_argument("--ht", type=positive_int, default=3, help="trajectory horizon H_t")
    build.add_argument("--hu", type=positive_int, help="control horizon H_u (default: H_t)")
    build.add_argument("--hp", type=positive_int, default=50, help="prediction horizon H_p")
    build.add_argument("--ert", choices=["foh", "zoh"], default="foh",
                       help="extended reference trajectory")
    build.add_argument("--umax", type=positive_float, default=1000.0,
                       help="current limit |u| <= umax [mA]")
    build.add_argument("--box", help=BOX_HELP)
    build.add_argument("--json", action="store_true", help="print the figures as JSON")
    build.add_argument("--export-c", metavar="F.c", help="write the law as C99 source")
    build.set_defaults(handler=build_command)


def build_command(args: argparse.Namespace) -> int:
    from hil.controllers.servo.empc import build_explicit_law
    from hil.controllers.servo.empc_export import write_c
    from hil.controllers.servo.mpc import MpcConfig

    if args.export_c and not Path(args.export_c).resolve().parent.is_dir():
        raise UsageError(f"--export-c {args.export_c}: no such directory")
    hu = args.hu or args.ht
    config = MpcConfig(ht=args.ht, hu=hu, hp=args.hp, ert=args.ert, u_min=-args.umax,
                       u_max=args.umax)
    law = build_explicit_law(config, box=args.box)
    result = law.summary()
    if args.export_c:
        result["c_file"] = str(write_c(law, args.export_c))
    if args.json:
        print(json_text(result))
        return 0
    print(f"explicit MPC  H_t = {config.ht}, H_u = {config.hu}, H_p = {config.hp}, "
          f"{config.ert.upper()}, |u| <= {args.umax:g} mA")
    for key in ("regions", "controllers", "tree_nodes", "tree_leaves", "tree_depth",
                "hyperplanes", "build_s", "mpqp_s", "tree_s"):
        print(f"  {key:<12} {result[key]}")
    print("  box          " + ", ".join(f"{k} [{lo:g}, {hi:g}]"
                                        for k, (lo, hi) in result["box"].items()))
    if args.export_c:
        print(f"  C source     {result['c_file']}")
    return 0
