"""``hil servo run``: trajectory tracking on the servo drive."""

from __future__ import annotations

import argparse

from hil.commands import not_yet_available
from hil.commands.argtypes import positive_float, positive_int


def register(subparsers: argparse._SubParsersAction) -> None:
    servo = subparsers.add_parser("servo", help="servo drive: closed-loop tracking runs")
    servo_sub = servo.add_subparsers(dest="servo_command", metavar="COMMAND", required=True)
    srun = servo_sub.add_parser("run", help="run MPC, explicit MPC or PID against the drive")
    srun.add_argument("--controller", choices=["mpc", "empc", "pid"], required=True)
    srun.add_argument("--drive", default="emulated", help="emulated | socketcand://HOST:PORT")
    srun.add_argument("--node", type=positive_int, default=1, help="CANopen node id")
    srun.add_argument("--ert", choices=["foh", "zoh"], default="foh")
    srun.add_argument("--ht", type=positive_int, default=8, help="trajectory horizon")
    srun.add_argument("--hu", type=positive_int, default=8, help="control horizon")
    srun.add_argument("--hp", type=positive_int, default=50, help="prediction horizon")
    srun.add_argument("--umax", type=positive_float, default=1000.0, help="current limit [mA]")
    srun.add_argument("--reference", default="sine:amplitude=2,frequency=10")
    srun.add_argument("--duration", type=positive_float, default=2.0, help="[s]")
    srun.add_argument("--realtime", action="store_true")
    srun.add_argument("--out", metavar="F.mcap")
    srun.add_argument("--json", action="store_true")
    srun.set_defaults(handler=not_yet_available("hil servo run"))
