"""Modbus poll round trips (TCP loopback, RTU 115200 on a pty) and 100 Hz bench sampling.

The emulator runs as its own process (``hil emulate bench``), like the hardware it replaces.
Round trips: each transport's figure is printed next to a baseline measured in the same run
(a hand-made frame on a raw socket or serial port; for a paced RTU line, the wire time of the
frames). Sampling: a real-time session at 100 Hz polls the meter and the levels for
``--duration`` s against the TCP emulator, next to the same loop without I/O, then briefly
over a paced RTU line. Target (the project's): TCP poll p99 <= 2 ms. The machine is shared:
figures are noisy, run it on a quiet box for figures worth quoting. ``--quick``: 20 TCP and
5 RTU round trips per row (the driver waiting up to 2 s for each answer), sampling runs of
0.2 s each (seconds; figures not worth quoting).

Lockstep over the wire, clean line: a lockstep ``hil bench run --controller bc`` against
``hil emulate bench`` over TCP and over RTU (a pty pair), this code (numbered time requests,
answers matched by hil) against the code before the time protocol's last revision (``git
archive`` of that commit's parent, or ``--baseline-code DIR``), alternated, in the same run:
each one's realtime factor (simulated time over the loop's time), the median of ``--repeat``,
and after/before (above 1: faster now). ``--quick``: one run of a 2 s cycle each, this code
only.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np
import serial
from benchkit import (
    REPO,
    add_baseline_code,
    add_quick,
    baseline_code,
    code_before,
    fill_defaults,
    git,
)
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.framer.rtu import FramerRTU

from hil.bench.config import BenchConfig, load_bench_config, parse_bench_config
from hil.bench.rig import attach_bench
from hil.core.clock import RealtimeClock
from hil.core.config import deep_merge
from hil.core.loop import FunctionTask
from hil.core.session import Session
from hil.core.stats import percentile_summary
from hil.drivers.bench.modbus import ModbusLink, parse_bus_url

ENV = {**os.environ, "PYTHONPATH": str(REPO), "PYTHONUNBUFFERED": "1"}
METER_UNIT, FULL, SMALL = 2, 76, 6   # whole SDM630 map in one request; va_l1..va_l3

def spawn(*args: str, code: Path = REPO, quiet: bool = False
          ) -> tuple[subprocess.Popen[str], str]:
    """``python ARGS`` with the checkout at ``code`` on the path (``quiet``: its stderr
    dropped); its first line."""
    proc = subprocess.Popen([sys.executable, *args], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, cwd=code,
                            stderr=subprocess.DEVNULL if quiet else None,
                            env={**ENV, "PYTHONPATH": str(code)})
    assert proc.stdout is not None  # stdout=PIPE
    return proc, proc.stdout.readline().strip()


def emulator(*where: str, code: Path = REPO, quiet: bool = False
             ) -> tuple[subprocess.Popen[str], str]:
    proc, line = spawn("-m", "hil", "emulate", "bench", *where, code=code, quiet=quiet)
    match = re.search(r"listening on (\S+)", line)
    if not match:
        raise SystemExit(f"emulator did not start: {line!r}")
    return proc, match.group(1)


def null_modem(baud: int | None) -> tuple[subprocess.Popen[str], list[str]]:
    """A pty pair in a helper process (its copy threads then do not share our GIL)."""
    code = ("import sys; from hil.emulators.null_modem import NullModem\n"
            f"m = NullModem(baudrate={baud!r}); print(' '.join(m.ports), flush=True)\n"
            "sys.stdin.read(); m.close()")
    proc, line = spawn("-c", code)
    return proc, line.split()


def stop(proc: subprocess.Popen[str]) -> None:
    if proc.stdin is not None:  # the null modem helper ends when its stdin closes
        proc.stdin.close()
    proc.terminate()
    try:
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        proc.kill()


def time_calls(call: Callable[[], object], n: int) -> np.ndarray:
    for _ in range(min(50, n)):
        call()
    out = np.empty(n)
    for i in range(n):
        t0 = time.perf_counter_ns()
        call()
        out[i] = (time.perf_counter_ns() - t0) / 1e3
    return out


def row(name: str, samples_us: np.ndarray, note: str = "") -> None:
    s = percentile_summary(samples_us)
    print(f"  {name:<54} {s['p50']:>9.0f} {s['p99']:>9.0f} {s['max']:>9.0f}  {note}")


def header(title: str) -> None:
    print(f"\n{title}\n  {'':<54} {'p50 us':>9} {'p99 us':>9} {'max us':>9}")


def raw_tcp(port: int) -> Callable[[], bytes]:
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    request = struct.pack(">HHHBBHH", 1, 0, 6, METER_UNIT, 4, 0, FULL)
    size = 9 + 2 * FULL

    def call() -> bytes:
        sock.sendall(request)
        data = b""
        while len(data) < size:
            data += sock.recv(size - len(data))
        return data

    return call


def raw_rtu(port: str, count: int) -> Callable[[], bytes]:
    line = serial.Serial(port, 115200, timeout=1)
    frame = bytes([METER_UNIT, 4, 0, 0, 0, count])
    request = frame + FramerRTU.compute_CRC(frame).to_bytes(2, "big")
    size = 5 + 2 * count

    def call() -> bytes:
        line.write(request)
        return line.read(size)

    return call


def round_trips(n_tcp: int, n_rtu: int, patient: bool = False) -> None:
    """``patient`` (``--quick``): the hil driver waits 2 s for an answer, not 0.1 s (TCP) and
    0.2 s (RTU): on a loaded machine (make test) an emulator answers late, and a quick run
    checks that the benchmark runs, not the machine's pace."""
    header("Poll round trip, meter unit (FC04)")
    proc, url = emulator("--tcp", "127.0.0.1:0")
    try:
        port = parse_bus_url(url).port
        row(f"TCP raw socket frame ({FULL} regs) [baseline]", time_calls(raw_tcp(port), n_tcp))
        client = ModbusTcpClient("127.0.0.1", port=port, timeout=1, retries=0)
        client.connect()
        row(f"TCP pymodbus client ({FULL} regs)", time_calls(
            lambda: client.read_input_registers(0, count=FULL, device_id=METER_UNIT), n_tcp))
        client.close()
        link = ModbusLink(parse_bus_url(url), timeout_s=2.0 if patient else 0.1, attempts=2)
        samples = time_calls(lambda: link.read_floats(METER_UNIT, 0, FULL), n_tcp)
        row(f"TCP hil driver ({FULL} regs)", samples,
            f"target p99 <= 2000 us: {'met' if np.percentile(samples, 99) <= 2000 else 'MISSED'}")
        link.close()
    finally:
        stop(proc)
    for baud in (None, 115200):
        modem, ports = null_modem(baud)
        proc, url = emulator("--serial", ports[1], "--baud", "115200")
        kind = "RTU pty" if baud is None else "RTU pty paced at 115200 8N1"
        try:
            if baud is None:
                row(f"{kind}: raw frame ({FULL} regs) [baseline]",
                    time_calls(raw_rtu(ports[0], FULL), n_rtu))
                serial_client = ModbusSerialClient(ports[0], baudrate=115200, timeout=1,
                                                   retries=0)
                serial_client.connect()
                row(f"{kind}: pymodbus client ({FULL} regs)", time_calls(
                    partial(serial_client.read_input_registers, 0, count=FULL,
                            device_id=METER_UNIT), n_rtu))
                serial_client.close()
            link = ModbusLink(parse_bus_url(f"modbus-rtu://{ports[0]}?baud=115200"),
                              timeout_s=2.0 if patient else 0.2, attempts=2)
            for count in (FULL, SMALL):
                n = n_rtu if baud is None else max(min(50, n_rtu), n_rtu // 5)
                wire_us = (8 + 5 + 2 * count) * 10 / 115200 * 1e6
                note = "" if baud is None else f"wire time of the frames {wire_us:.0f} us"
                first = 0x12 if count == SMALL else 0
                row(f"{kind}: hil driver ({count} regs)", time_calls(
                    partial(link.read_floats, METER_UNIT, first, count), n), note)
            link.close()
        finally:
            stop(proc)
            stop(modem)


def loop_only(duration_s: float) -> tuple[dict, int, int]:
    with tempfile.TemporaryDirectory() as tmp:
        session = Session(f"{tmp}/idle.mcap", RealtimeClock(), 0.01, kind="bench",
                          handle_signals=False)
        session.add_task(FunctionTask("bench_io", 1))
        session.run(duration_s=duration_s)
        session.close()
        stats = session.loop.stats["bench_io"]
        return stats.lateness.summary(), stats.runs, stats.missed


def sampling(url: str, duration_s: float, config: BenchConfig
             ) -> tuple[dict, int, int, int, int]:
    with tempfile.TemporaryDirectory() as tmp:
        session = Session(f"{tmp}/b.mcap", RealtimeClock(), 0.01, kind="bench",
                          config=config.data, handle_signals=False)
        rig = attach_bench(session, config, url)
        session.run(duration_s=duration_s)
        rig.close()
        session.close()
        stats = session.loop.stats["bench_io"]
        late = sum(int(np.count_nonzero(np.asarray(m["lateness_us"]) > 5000))
                   for m in _timing_messages(session))
        return (stats.lateness.summary(), stats.runs, stats.missed,
                rig.sampler.missed_power, late)


def _timing_messages(session: Session) -> list[dict]:
    from hil.core.recording.reader import read_session

    return [m for _, m in read_session(session.path).topic("/loop/bench_io/timing")]


def sampling_report(duration_s: float, rtu_s: float) -> None:
    print(f"\n100 Hz sampling (meter + levels every 10 ms, real time, recorded)\n"
          f"  {'':<54} {'samples':>8} {'missed':>7} {'failed':>7} {'>5ms':>6} "
          f"{'p50 us':>7} {'p99 us':>7} {'max us':>8}")

    def line(name: str, lat: dict, runs: int, missed: int, failed: str, late: str) -> None:
        print(f"  {name:<54} {runs:>8} {missed:>7} {failed:>7} {late:>6} "
              f"{lat['p50']:>7.0f} {lat['p99']:>7.0f} {lat['max']:>8.0f}")

    lat, runs, missed = loop_only(min(5.0, duration_s))
    line(f"loop without I/O, {min(5.0, duration_s):g} s [baseline]", lat, runs, missed, "-", "-")
    config = load_bench_config()
    proc, url = emulator("--tcp", "127.0.0.1:0")
    try:
        lat, runs, missed, failed, late = sampling(url, duration_s, config)
        line(f"TCP emulator process, {duration_s:g} s", lat, runs, missed, str(failed),
             str(late))
    finally:
        stop(proc)
    modem, ports = null_modem(115200)
    proc, _ = emulator("--serial", ports[1])
    small = parse_bench_config(deep_merge(config.data, {
        "meter": {"poll": ["va_l1", "va_l2", "va_l3"]}, "sampling": {"levels_every": 10}}))
    try:
        lat, runs, missed, failed, late = sampling(f"modbus-rtu://{ports[0]}?baud=115200",
                                                   rtu_s, small)
        line(f"RTU paced 115200, VA only, levels 10 Hz, {rtu_s:g} s", lat, runs, missed,
             str(failed), str(late))
    finally:
        stop(proc)
        stop(modem)
    print("  missed = loop ticks skipped (the previous sample overran 10 ms); failed = polls "
          "without an answer; >5ms = samples started more than 5 ms late")


#: a 2 s machining cycle: --quick's lockstep runs
SHORT_CYCLE = """[sequence]
period_s = 2.0
stages = [{ start_s = 0.0, end_s = 1.0, on = [] },
          { start_s = 1.0, end_s = 2.0, on = ["M1", "M2"] }]
[relays.M1]
dwell_s = 0.5
[relays.M2]
dwell_s = 0.5
"""


def code_before_time_protocol(folder: Path) -> tuple[Path | None, str]:
    """The code before the time protocol's last revision (the parent of the last commit that
    changed ``REVISION`` in hil/protocols/bench_clock.py), extracted into ``folder`` with
    ``git archive``; (None, why not) outside a git checkout."""
    try:
        change = git("log", "-1", "--format=%H", "-G", "^REVISION = ", "HEAD", "--",
                     "hil/protocols/bench_clock.py")
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"not a git checkout ({exc})"
    if not change:
        return None, "no earlier time protocol in this checkout's history"
    code, ref = code_before(change, folder)
    if code is None:
        return None, ref
    revision = re.search(r'REVISION = "([^"]+)"',
                         (folder / "hil/protocols/bench_clock.py").read_text())
    return folder, f"{ref}, time protocol {revision.group(1) if revision else '?'}"


def lockstep_run(code: Path, transport: str, cycles: int, config: Path | None) -> float:
    """One lockstep ``hil bench run --controller bc`` against ``hil emulate bench`` over
    ``transport`` (tcp, or rtu on an unpaced pty pair), both of the checkout at ``code``: its
    realtime factor."""
    flags = ["--config", str(config)] if config is not None else []
    modem = None
    if transport == "tcp":
        proc, url = emulator("--tcp", "127.0.0.1:0", *flags, code=code, quiet=True)
    else:
        modem, ports = null_modem(None)
        proc, _ = emulator("--serial", ports[1], *flags, code=code, quiet=True)
        url = f"modbus-rtu://{ports[0]}"
    try:
        with tempfile.TemporaryDirectory() as tmp:
            done = subprocess.run(
                [sys.executable, "-m", "hil", "bench", "run", "--controller", "bc", "--cycles",
                 str(cycles), "--bench", url, "--json", "--quiet", "--out", f"{tmp}/run.mcap",
                 *flags], capture_output=True, text=True, cwd=tmp, stdin=subprocess.DEVNULL,
                env={**ENV, "PYTHONPATH": str(code)})
        kpis = json.loads(done.stdout) if done.stdout.startswith("{") else {}
        if kpis.get("status") != "completed":
            raise SystemExit(f"lockstep run over {transport} ({code}) did not complete: "
                             f"{done.stderr.strip()[-500:]}")
        return float(kpis["realtime_factor"])
    finally:
        stop(proc)
        if modem is not None:
            stop(modem)


def lockstep_protocols(cycles: int, repeat: int, baseline: Path | None, quick: bool) -> None:
    """This code's lockstep runs over TCP and RTU against the baseline's, alternated."""
    with tempfile.TemporaryDirectory() as tmp:
        config = None
        if quick:
            config = Path(tmp) / "short.toml"
            config.write_text(SHORT_CYCLE)
            before, why = None, "skipped (--quick)"
        else:
            before, why = baseline_code(baseline, Path(tmp), code_before_time_protocol)
        length = "2 s" if quick else "28 s"
        print(f"\nLockstep over the wire, clean line (bc, {cycles} cycle(s) of {length}; median "
              f"of {repeat}, alternated): realtime factor\n  before: {why}")
        for transport in ("tcp", "rtu"):
            after_x, before_x = [], []
            for _ in range(repeat):
                if before is not None:
                    before_x.append(lockstep_run(before, transport, cycles, config))
                after_x.append(lockstep_run(REPO, transport, cycles, config))
            after = statistics.median(after_x)
            line = f"  {transport.upper():<4} after (numbered time requests) {after:6.2f}x"
            if before_x:
                old = statistics.median(before_x)
                line += f"   before {old:6.2f}x   after/before {after / old:.2f}"
            print(line)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--duration", type=float,
                        help="TCP sampling run [s] (default 30; 0.2 with --quick)")
    parser.add_argument("--rtu-duration", type=float,
                        help="RTU sampling run [s] (default 10; 0.2 with --quick)")
    parser.add_argument("--polls", type=int,
                        help="TCP round trips per row (default 3000; 20 with --quick)")
    parser.add_argument("--rtu-polls", type=int,
                        help="RTU round trips per row (default 600; 5 with --quick)")
    parser.add_argument("--cycles", type=int,
                        help="machine cycles of each lockstep run (default 1)")
    parser.add_argument("--repeat", type=int,
                        help="lockstep runs of each code and transport (default 3; 1 with "
                             "--quick)")
    add_baseline_code(parser, "the code before the time protocol's last revision; for the "
                      "lockstep runs")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"duration": (30.0, 0.2), "rtu_duration": (10.0, 0.2),
                         "polls": (3000, 20), "rtu_polls": (600, 5), "cycles": (1, 1),
                         "repeat": (3, 1)})
    started = time.monotonic()
    round_trips(args.polls, args.rtu_polls, patient=args.quick)
    sampling_report(args.duration, args.rtu_duration)
    lockstep_protocols(args.cycles, args.repeat, args.baseline_code, args.quick)
    print(f"\n(total {time.monotonic() - started:.0f} s; shared machine: figures are noisy)")


if __name__ == "__main__":
    main()
