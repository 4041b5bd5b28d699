"""``hil servo run`` (tracking on the drive) and ``hil servo figures`` (paper Figs. 7-8)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from hil.cli.argtypes import key_value, output_file, positive_float, positive_int
from hil.cli.output import add_quiet_argument, json_text
from hil.cli.place import add_place_arguments, run_on_place
from hil.cli.recording import add_recording_arguments
from hil.cli.units import milliamps, seconds, seconds_or_zero
from hil.cli.verdict import add_controller_arguments, add_junit_argument
from hil.core.kpi_text import limit_text
from hil.core.recording.writer_fork import start_server
from hil.errors import UsageError

if TYPE_CHECKING:
    from hil.cli.application import RunApplication
    from hil.servo.run import ServoRunOptions


def register(subparsers: argparse._SubParsersAction) -> None:
    servo = subparsers.add_parser("servo", help="servo drive: closed-loop tracking runs")
    servo_sub = servo.add_subparsers(dest="servo_command", metavar="COMMAND", required=True)
    srun = servo_sub.add_parser(
        "run", help="run a controller (MPC, explicit MPC, PID or your own) against the drive",
        description="Close the loop through the CiA 402 drive link at T = master.cycle_period_us "
        "(500 us, the published axis model's, unless configured): read the "
        "drive's feedback, step the controller, send the current command. Lockstep by default "
        "(virtual time, as fast as the computer allows, deterministic); --realtime follows the "
        "wall clock. Records /drive/command, /drive/feedback, /mpc/prediction and /events to "
        "an MCAP session; prints the tracking KPIs. The controller is a built-in (mpc: "
        "trajectory MPC with an online QP, empc: explicit MPC, pid: cascaded PID + notch) or "
        "your own class with step(position_deg, t_s) -> current_mA, built as "
        "Class(reference, params); its currents are clamped by the driver whatever it asks. "
        "Safety limits (drive.toml [safety], --safety) are on by default. Exit status: 0 "
        "completed (every --limit holds), 1 a --limit is violated, 2 the run could not start "
        "or was stopped (bad flag or config, the drive faulted after an EMCY, a safety limit, "
        "lost link, recording failed, another master), 3 completed with faults (stale "
        "feedback, an EMCY the drive rode through), 130 interrupted.",
    )
    add_run_arguments(srun)
    add_junit_argument(srun)
    srun.add_argument("--out", metavar="F.mcap", type=output_file,
                      help="session file (default: sessions/servo-CONTROLLER-DATE-TIME.mcap)")
    srun.add_argument("--json", action="store_true", help="print the KPIs as JSON")
    srun.add_argument("--print-config", action="store_true",
                      help="print every setting as the run would use it, with where it came "
                      "from (built-in default, hil/configs/drive.toml, --config, a flag), and "
                      "exit without running; with --json as JSON")
    srun.add_argument("--axes", metavar="NAME=NODE,...",
                      help="several axes on one bus, one drive each, one SYNC per tick "
                      "(x=1,y=2): the controller runs on every axis with its reference; "
                      "--reference circle:radius=R,feed=F is a circular test on two axes "
                      "(R deg, F deg/s along the path; KPIs: the contour error); topics "
                      "/axis/NAME/..., KPIs per axis; a stop stops every axis in the same "
                      "cycles; NAME=NODE@URL puts an axis on a bus of its own. Without it: "
                      "the config's [[axis]] tables, else the one drive of [master] node_id")
    add_recording_arguments(srun)
    add_place_arguments(srun, "drive")
    srun.set_defaults(handler=run_command)

    register_identify(servo_sub)

    figs = servo_sub.add_parser(
        "figures", help="regenerate the paper's Figs. 7-8 table (offline simulation)",
        description="Normalised cumulative tracking error vs trajectory horizon H_t (= H_u) for "
        "cascaded PID and MPC with ZOH and FOH extended reference trajectory, on a sine of "
        "the given amplitude at 1 Hz (1000 mA limit) and 10 Hz (rated 12 A, and the printed "
        "1000 mA, where tracking needs more current than allowed), simulated on the published "
        "axis model. 1.0 = MPC set-point tracking (ZOH, H_t = 1), as in the paper.",
    )
    figs.add_argument("--hp", type=positive_int, default=50, help="prediction horizon")
    figs.add_argument("--max-ht", type=positive_int, default=8,
                      help="largest trajectory horizon of the sweep (from 1)")
    figs.add_argument("--q", type=positive_float, default=1e6, help="output weight Q(i)")
    figs.add_argument("--r", type=positive_float, default=1.0, help="input-move weight R(i)")
    figs.add_argument("--amplitude", type=positive_float, default=2.0, help="sine amplitude [deg]")
    figs.add_argument("--out", metavar="F.png", type=output_file,
                      help="also draw the table to this PNG file")
    figs.add_argument("--json", action="store_true", help="print the table as JSON")
    figs.add_argument("--workers", type=positive_int, default=1,
                      help="points simulated at once: 1 (default) in this process, more as a "
                      "sweep on a local Ray (pip install 'hil[sweep]')")
    figs.add_argument("--address", metavar="ADDR",
                      help="run the points on this Ray cluster (auto or ray://HOST:PORT)")
    figs.set_defaults(handler=figures_command)


def register_identify(servo_sub: argparse._SubParsersAction) -> None:
    """``hil servo identify``: the identification experiment, a servo run of its own."""
    from hil.controllers.servo.excitation_defaults import (
        DEFAULT_AMPLITUDE_MA,
        DEFAULT_DURATION_S,
        DEFAULT_KD_MA_PER_DEG_S,
        DEFAULT_KP_MA_PER_DEG,
        DEFAULT_SEED,
        KINDS,
        STABILISER_SHARE,
    )

    ident = servo_sub.add_parser(
        "identify", help="excite the axis in CST and record a session to identify it from",
        description="Record an identification experiment on the drive: a current excitation "
        "(CST) plus a weak stabilising loop (PD on the position) that keeps the axis near "
        "where it started, for 'hil identify F.mcap --servo' to make a model of the axis "
        "from. It is a servo run like 'hil servo run' (same drive URLs, lockstep or "
        "--realtime, safety limits, current clamp, safe stop, MCAP session), its controller "
        "the excitation, its reference held where the axis starts. The command's peak is the "
        f"amplitude plus the stabiliser's share ({STABILISER_SHARE * 100:g} % of the amplitude): "
        "an amplitude whose peak does not fit inside the current limit is refused. Exit "
        "status as 'hil servo run': 0 completed, 2 refused or stopped (a safety limit, a "
        "fault), 3 completed with faults, 130 interrupted.")
    ident.add_argument("--excitation", choices=KINDS,
                       help="prbs (default: crest factor 1, the most power a current limit "
                       "allows, flat up to 0.44/T), multisine (Schroeder phases, 0.5 Hz to "
                       "0.45/T) or chirp (linear sweep 1 Hz to 0.45/T)")
    ident.add_argument("--amplitude", type=milliamps, metavar="MA",
                       help=f"peak current of the excitation [mA] (default "
                       f"{DEFAULT_AMPLITUDE_MA:g}); the stabiliser adds up to "
                       f"{STABILISER_SHARE * 100:g} %% of it")
    ident.add_argument("--seed", type=positive_int, metavar="N",
                       help=f"the PRBS's start state (default {DEFAULT_SEED}; taken modulo its "
                       "period, 32767): the same seed, the same excitation")
    ident.add_argument("--duration", type=seconds, metavar="S",
                       help=f"length of the experiment [s] (default {DEFAULT_DURATION_S:g})")
    ident.add_argument("--param", action="append", type=key_value, default=[],
                       metavar="KEY=VALUE",
                       help="the stabiliser's gains: kp [mA/deg] (default "
                       f"{DEFAULT_KP_MA_PER_DEG:g}), kd [mA per deg/s] (default "
                       f"{DEFAULT_KD_MA_PER_DEG_S:g}); about 2 Hz on the published axis")
    ident.add_argument("--umax", type=milliamps, metavar="MA",
                       help="current limit [mA] (default: [master] current_limit_mA, 1000): "
                       "may only lower the configured limit")
    ident.add_argument("--safety", action="append", type=key_value, default=[],
                       metavar="KEY=VALUE",
                       help="tighten one safety limit of drive.toml's [safety] (repeat), as "
                       "'hil servo run --safety'; following_error_deg is the distance from "
                       "where the axis started; never loosened")
    add_drive_arguments(ident)
    add_device_arguments(ident)
    add_clock_arguments(ident)
    add_config_argument(ident)
    ident.add_argument("--out", metavar="F.mcap", type=output_file,
                       help="session file (default: sessions/servo-excitation-DATE-TIME.mcap)")
    ident.add_argument("--json", action="store_true", help="print the run's KPIs as JSON")
    ident.add_argument("--print-config", action="store_true",
                       help="print every setting as the run would use it, and exit")
    add_junit_argument(ident)
    add_recording_arguments(ident)
    add_place_arguments(ident, "drive")
    ident.set_defaults(handler=servo_identify_command)


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """The flags of ``hil servo run`` that make up the experiment (shared with ``hil sweep
    servo``): the controller, its tuning, the drive, the reference and the verdict."""
    add_controller_arguments(parser, "mpc, empc, pid (currents, CST), setpoint (the reference "
                             "as a position or velocity set point: CSP, CSV, PV)",
                             "abs_error_deg, abs_command_mA, "
                             "abs_velocity_deg_s, position_deg")
    add_drive_arguments(parser)
    parser.add_argument("--safety", action="append", type=key_value, default=[],
                        metavar="KEY=VALUE",
                        help="tighten one safety limit of drive.toml's [safety] for this run "
                        "(repeat): following_error_deg, following_error_ms, position_min_deg, "
                        "position_max_deg, velocity_max_deg_s, stale_share_max, "
                        "stale_window_ms, enabled; a looser value needs "
                        "--allow-looser-safety")
    parser.add_argument("--allow-looser-safety", action="store_true",
                        help="let --safety loosen a limit of the config (recorded as a "
                        "warning in the session)")
    add_device_arguments(parser)
    parser.add_argument("--ert", choices=["foh", "zoh"],
                        help="extended reference trajectory: first- or zero-order hold "
                        "(default foh)")
    parser.add_argument("--ht", type=positive_int,
                        help="trajectory horizon [ticks] (default 8; 3 for empc, as the "
                        "paper's drive)")
    parser.add_argument("--hu", type=positive_int,
                        help="control horizon [ticks] (default 8; 3 for empc, as the paper's "
                        "drive)")
    parser.add_argument("--hp", type=positive_int, help="prediction horizon [ticks] "
                        "(default 50)")
    parser.add_argument("--umax", type=milliamps, metavar="MA",
                        help="current limit [mA]: the controller's bounds and the driver's "
                        "clamp (default: [master] current_limit_mA, 1000); may lower the "
                        "configured limit, not raise it without --allow-higher-current")
    parser.add_argument("--allow-higher-current", action="store_true",
                        help="let --umax raise the configured current limit (recorded as a "
                        "warning in the session)")
    parser.add_argument("--reference",
                        help="default: the paper's 1 Hz sine of 2 deg (its Fig. 7 case), which "
                        "the built-in controllers track within a few percent; the 10 Hz case "
                        "(Fig. 8, sine:amplitude=2,frequency=10) asks the emulated axis for more "
                        "than its 1000 mA allow. "
                        "sine:amplitude=A,frequency=F | trapezoid:stroke=DEG,speed=RPM (a "
                        "negative stroke moves the other way) | "
                        "disturbance:torque=MA,start=S,end=S (Fig. 16: hold while a torque pulse "
                        "pushes the axis; emulated drives) | hold:position=DEG | "
                        "circle:radius=DEG,feed=DEG_PER_S (with --axes: a circular test on "
                        "two axes)")
    parser.add_argument("--from-here", action="store_true",
                        help="the reference is relative to where the axis stands when the run "
                        "starts (default: an angle of the spindle, on the turn nearest it)")
    parser.add_argument("--home", action="store_true",
                        help="home the axis first (homing mode, HM: [homing] method, offset, "
                        "speeds; as 'hil drive home'), then run in [master] mode with the "
                        "reference absolute from home (not with --from-here)")
    parser.add_argument("--duration", type=seconds, metavar="S",
                        help="length of the run [s] (default 2)")
    parser.add_argument("--settle", type=seconds_or_zero, metavar="S",
                        help="KPIs ignore the first S seconds [s] (start-up transient; "
                        "default 0)")
    add_clock_arguments(parser)
    parser.add_argument("--prediction-every", type=positive_int, metavar="N",
                        help="record /mpc/prediction every N ticks (default: every tick in "
                        "lockstep, every 10th in real time)")
    add_config_argument(parser)


def add_drive_arguments(parser: argparse.ArgumentParser) -> None:
    """``--drive`` and ``--can-log`` (every servo run)."""
    parser.add_argument("--drive", metavar="URL",
                        help="where the drive is (default: drive.toml's [bus], emulated): "
                        "emulated (hil's emulator: in this process in lockstep, in a process "
                        "of its own with --realtime) | socketcand://HOST:PORT[/CHANNEL] | "
                        "INTERFACE://CHANNEL[?key=value&...] for any python-can interface, "
                        "e.g. socketcan://can0, pcan://PCAN_USBBUS1, kvaser://0, gs_usb://0, "
                        "slcan:///dev/ttyACM0?bitrate=1000000, serial:///dev/ttyUSB0, "
                        "udp_multicast://239.0.0.1?port=43113, virtual://NAME (query keys are "
                        "keyword arguments of python-can's can.Bus)")
    parser.add_argument("--can-log", metavar="F.blf|F.asc|F.trc|F.log", type=output_file,
                        help="write every CAN frame of the run to this file (python-can's "
                        "can.Logger; the suffix picks the format: opens in can.player, "
                        "can.viewer, Vector and PEAK tools); with axes on several buses, one "
                        "file a bus: F, then STEM-bus2.SUFFIX...")


def add_device_arguments(parser: argparse.ArgumentParser) -> None:
    """``--reset-fault``, ``--node``, ``--eds`` (every servo run)."""
    parser.add_argument("--reset-fault", action="store_true",
                        help="clear a drive left in FAULT (CiA 402 fault reset) before "
                        "enabling it")
    parser.add_argument("--node", type=positive_int,
                        help="the drive's CANopen node id (default: [master] node_id, 1)")
    parser.add_argument("--eds", metavar="F.eds",
                        help="the drive's EDS or DCF: every object hil uses is checked in it "
                        "before the drive is configured (default: [master] eds)")


def add_clock_arguments(parser: argparse.ArgumentParser) -> None:
    """``--realtime`` and ``--quiet`` (every servo run)."""
    parser.add_argument("--realtime", action="store_true",
                        help="follow the wall clock (default: lockstep virtual time)")
    add_quiet_argument(parser)


def add_config_argument(parser: argparse.ArgumentParser) -> None:
    """``--config`` (every servo run)."""
    parser.add_argument("--config", metavar="F.toml",
                        help="drive config laid over the default (hil/configs/drive.toml)")


def application() -> RunApplication[ServoRunOptions]:
    """``hil servo run``'s application (its modules load here)."""
    from hil.cli.application import RunApplication
    from hil.servo.run import ServoRunOptions, run_servo
    from hil.servo.settings import resolve_servo

    def summary(options: ServoRunOptions, kpis: dict[str, Any]) -> str:
        several = "axes" in kpis
        return format_axes_run(options, kpis) if several else format_run(options, kpis)

    return RunApplication("hil servo run", ServoRunOptions.from_flags,
                          lambda options: resolve_servo(options).settings(), run_servo,
                          summary)


def run_command(args: argparse.Namespace) -> int:
    start_server()  # beside this command's imports: its first session finds it up
    return run_on_place(args, "servo", lambda: application().command_line(args))


def servo_identify_command(args: argparse.Namespace) -> int:
    """``hil servo identify``: the excitation as a servo run."""
    start_server()  # beside this command's imports: its first session finds it up
    from hil.cli.application import RunApplication
    from hil.controllers.servo.excitation_defaults import DEFAULT_AMPLITUDE_MA, DEFAULT_KIND
    from hil.servo.identify import identify_options, identify_settings
    from hil.servo.run import run_servo

    def summary(options: ServoRunOptions, kpis: dict[str, Any]) -> str:
        params = dict(options.params)
        rest = format_run(options, kpis).splitlines()[1:]
        amplitude = params.get("amplitude", DEFAULT_AMPLITUDE_MA)
        lines = [f"servo identify: {params.get('kind', DEFAULT_KIND)} excitation, amplitude "
                 f"{amplitude:g} mA, |u| <= {kpis['umax_mA']:g} mA, "
                 f"drive {kpis['drive']}, clock {kpis['clock']}",
                 *(line.replace("  error:", "  distance from the start:") for line in rest),
                 f"  identify the axis: hil identify {kpis['mcap']} --servo"]
        return "\n".join(lines)

    application = RunApplication("hil servo identify", identify_options,
                                 lambda options: identify_settings(options, vars(args)),
                                 run_servo, summary)
    return run_on_place(args, "servo", lambda: application.command_line(args))


def format_axes_run(config: Any, kpis: dict[str, Any]) -> str:
    """The human summary of ``hil servo run --axes``."""
    lines = [f"servo run on {len(kpis['axes'])} axes: {config.describe_controller()}, "
             f"{kpis['reference']}, drive {kpis['drive']}, clock {kpis['clock']}",
             f"  ticks {kpis['ticks']}, {kpis['sync_cycles']} SYNC ({pace(kpis)}), "
             f"stopped: {kpis['stop_reason']}"]
    for name, axis in kpis["axes"].items():
        lines.append(f"  axis {name} (node {axis['node']}): error max "
                     f"{_deg(axis['max_error_deg'])}, rms {_deg(axis['rms_error_deg'])}; peak "
                     f"current {axis['peak_current_mA'] or 0:.0f} mA; stale feedback "
                     f"{axis['stale_feedback']}")
    contour = kpis.get("contour")
    if contour:
        lines.append(f"  contour error (circle of {contour['radius_deg']:g} deg): max "
                     f"{_deg(contour['max_contour_error_deg'])}, rms "
                     f"{_deg(contour['rms_contour_error_deg'])}")
    lines.append(f"  session {kpis['mcap']}")
    return "\n".join(lines)


def pace(kpis: dict[str, Any]) -> str:
    """The session time, the wall time and the real-time factor, in figures that agree: the
    factor is the session time over the time the loop ticked, which the whole run's wall time
    (start and safe stop included) exceeds: ``2.000 s in 0.43 s wall, the loop 0.37 s: 5.46x
    real time``."""
    session_s = kpis["ticks"] * kpis["cycle_period_us"] * 1e-6
    text = f"{session_s:.3f} s in {kpis['wall_s']:.2f} s wall"
    factor = kpis.get("realtime_factor")
    if not factor:
        return text
    return f"{text}, the loop {session_s / factor:.2f} s: {factor:.2f}x real time"


def _deg(value: float | None, digits: int = 4) -> str:
    return "-" if value is None else f"{value:.{digits}f} deg"


def _currents(kpis: dict[str, Any]) -> str:
    """The peak currents: sent and requested, or where the drive closed its own loop on the
    set points it was sent, the drive's."""
    if "set_point" in kpis:
        return (f"  {kpis['set_point']} set points, the drive's own loop: peak current "
                f"{kpis['peak_current_mA'] or 0:.0f} mA (torque actual)")
    return (f"  peak current sent {kpis['peak_current_mA'] or 0:.0f} mA (requested "
            f"{kpis['peak_requested_mA'] or 0:.0f} mA; clamped by the driver "
            f"{kpis['clamped_commands']} times)")


def format_run(config: Any, kpis: dict[str, Any]) -> str:
    """The human summary of ``hil servo run``."""
    pct = kpis["max_error_pct"]
    step = kpis["step_us"]
    lines = [
        f"servo run: {config.describe_controller()}, {kpis['reference']}, "
        f"|u| <= {kpis['umax_mA']:g} mA, drive {kpis['drive']}, clock {kpis['clock']}",
        f"  ticks {kpis['ticks']} ({pace(kpis)}), stopped: {kpis['stop_reason']}",
        f"  error{' after ' + format(kpis['settle_s'], 'g') + ' s' if kpis['settle_s'] else ''}"
        f": max {_deg(kpis['max_error_deg'])}"
        + (f" ({pct:.1f} % of the reference amplitude)" if pct is not None else "")
        + f", rms {_deg(kpis['rms_error_deg'])}, cumulative "
        f"{_deg(kpis['cumulative_error_deg'], 2)}",
        _currents(kpis) + f", stale feedback {kpis['stale_feedback']}",
        f"  controller step median/p99/max {step['median']:.1f}/{step['p99']:.1f}/"
        f"{step['max']:.1f} us, deadline misses {kpis['deadline_misses']}",
    ]
    if "solver_paths" in kpis:
        lines.append("  solver paths " + ", ".join(f"{k} {v}" for k, v in
                                                 kpis["solver_paths"].items()))
    if "empc_fallbacks" in kpis:
        lines.append(f"  explicit MPC fallbacks to the online QP: {kpis['empc_fallbacks']}")
    lines += [f"  limit {limit_text(row)}" for row in kpis.get("limits", [])]
    lines.append(f"  session {kpis['mcap']}")
    return "\n".join(lines)


def figures_command(args: argparse.Namespace) -> int:
    """``hil servo figures``: the preset sweep of :func:`hil.servo.demo.run_figures_sweep`."""
    from hil.servo.demo import run_figures_sweep
    from hil.sweep.engine import Engine

    if args.max_ht > args.hp:
        raise UsageError(f"--max-ht ({args.max_ht}) must not exceed --hp ({args.hp})")
    engine = Engine(workers=args.workers, address=args.address,
                    serial=args.workers == 1 and not args.address)
    table = run_figures_sweep(range(1, args.max_ht + 1), args.hp, args.q, args.r,
                              args.amplitude, engine)
    result = {"amplitude_deg": args.amplitude, "hp": args.hp, "q": args.q, "r": args.r,
              "cases": table}
    if args.out:
        plot_figures(table, args.out)
        result["png"] = args.out
    print(json_text(result) if args.json else format_figures(result))
    return 0


def _cell(value: float | None) -> str:
    return f"{value:>7.3f}" if value is not None else f"{'-':>7}"


def format_figures(result: dict[str, Any]) -> str:
    lines = [
        "Figs. 7-8: normalised cumulative tracking error over one cycle "
        "(1.000 = MPC set-point tracking, ZOH H_t = 1)",
        f"sine {result['amplitude_deg']:g} deg, H_t = H_u, H_p = {result['hp']}, "
        f"Q = {result['q']:g}, R = {result['r']:g}; published axis model, offline simulation",
    ]
    for case in result["cases"]:
        sp, ab = case["setpoint"], case["absolute"]
        lines += [
            "",
            f"{case['frequency_hz']:g} Hz, |u| <= {case['current_limit_mA']:g} mA   "
            f"(set-point MPC: cumulative {sp['cumulative_error_deg']:.3f} deg, "
            f"max {sp['max_error_deg']:.4f} deg, peak {sp['peak_current_mA']:.0f} mA)",
            "H_t     " + "".join(f"{h:>7}" for h in case["horizons"]),
            "ZOH     " + "".join(_cell(v) for v in case["zoh"]),
            "FOH     " + "".join(_cell(v) for v in case["foh"]),
            f"PID     {case['pid']:>7.3f}  (every H_t; max error {ab['pid']['max_error_deg']:.4f}"
            " deg)",
            f"PID+vff {case['pid_vff']:>7.3f}  (velocity feed-forward, not in Table I; max "
            f"error {ab['pid_vff']['max_error_deg']:.4f} deg)",
        ]
        best = ab["foh"][-1]
        if best is not None:
            lines.append(f"FOH H_t = {case['horizons'][-1]}: max error "
                         f"{best['max_error_deg']:.4f} deg, peak {best['peak_current_mA']:.0f} mA")
    return "\n".join(lines)


def plot_figures(table: list[dict[str, Any]], out_png: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import MaxNLocator

    fig, axes = plt.subplots(1, len(table), figsize=(4.6 * len(table), 3.8), squeeze=False)
    for ax, case in zip(axes[0], table, strict=True):
        hts = case["horizons"]
        foh = [(h, v) for h, v in zip(hts, case["foh"], strict=True) if v is not None]
        ax.plot(hts, case["zoh"], "o-", label="MPC ZOH-ERT")
        ax.plot([h for h, _ in foh], [v for _, v in foh], "s-", label="MPC FOH-ERT")
        ax.axhline(case["pid"], color="k", ls="--", label="cascaded PID")
        ax.axhline(case["pid_vff"], color="gray", ls=":", label="PID + vel. FF (not in paper)")
        ax.set_yscale("log")
        ax.set_xlabel("trajectory horizon H_t = H_u")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))  # a horizon is a whole count
        ax.set_title(f"{case['frequency_hz']:g} Hz, |u| <= {case['current_limit_mA']:g} mA")
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel("normalised cumulative error")
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
