"""What the tests of vendor drive files share, over CAN (tests/integration/test_vendor_drives.py:
EDS and DCF twins over socketcand) and over EtherCAT (tests/servo/test_vendor_esi_drives.py:
ESI twins over a veth pair): the matrix's "supplied" cell, the twin's folder (outside the
repository) and its commands, and the runs that prove a mode driven."""

from __future__ import annotations

import json
import subprocess
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from hil.core.recording.reader import read_session
from tests.cli import hil_here

#: what a 0.2 s run from where the axis stands must track the default 2 deg, 1 Hz sine within
#: (the reference alone: 1.3 deg; on a twin of 4096 increments a turn CSP lags by 0.3-0.45)
RMS_BOUND_DEG = {"CST": 1.0, "CSP": 0.7, "CSV": 0.3, "PV": 0.4}


def twinned_and_refused(matrix: Mapping[str, Any]) -> tuple[list[str], list[str]]:
    """The paths of a vendor matrix a twin is made of, and those it refuses (each entry's
    ``not_twinned`` says why, or is empty)."""
    return ([path for path, entry in matrix.items() if not entry.not_twinned],
            [path for path, entry in matrix.items() if entry.not_twinned])


def supplied_cell(supplied: dict[str, int], stand_ins: dict[str, Any]) -> str:
    """What a file needs besides, as the README's matrix shows it: the ``--set`` values (a
    device type in hex), then the ``[master]`` keys."""
    cells = [f"`--set {key}={value:#x}`" if key == "0x1000:0" else f"`--set {key}={value}`"
             for key, value in supplied.items()]
    cells += [f"`[master] {key} = {json.dumps(value)}`" for key, value in stand_ins.items()]
    return ", ".join(cells) or "-"


@dataclass
class TwinFolder:
    """A twin at ``url``, and the folder its commands run from (``main`` in this process);
    ``stand_ins``: the ``[master]`` keys for what its file lacks."""

    url: str
    folder: Path
    capsys: pytest.CaptureFixture[str]
    stand_ins: dict[str, Any]

    def config(self, mode: str, extra: str = "") -> str:
        """A config file in the folder: ``[master]`` mode and stand-ins, then ``extra``."""
        name = f"{mode}.toml"
        keys = "".join(f"{key} = {json.dumps(value)}\n" for key, value in self.stand_ins.items())
        (self.folder / name).write_text(f'[master]\nmode = "{mode}"\n{keys}{extra}')
        return name

    def hil(self, *args: object) -> subprocess.CompletedProcess[str]:
        return hil_here(self.capsys, *args, cwd=self.folder)

    def last_statusword(self, session: str) -> int:
        *_, (_, last) = read_session(str(self.folder / session)).topic("/drive/feedback")
        return int(last["statusword"])


def track(twin: TwinFolder, mode: str, profile: str = "") -> tuple[dict[str, Any], dict[str, str]]:
    """``hil servo run`` 0.2 s from where the axis stands, lockstep: CST with pid (hil's
    current every cycle), the others with ``setpoint`` (the reference as the drive's set
    point); tracked within :data:`RMS_BOUND_DEG`, every cycle fresh, on the master's time.
    The KPIs and the session's events (the last of each kind)."""
    ran = twin.hil("servo", "run", "--controller", "pid" if mode == "CST" else "setpoint",
                   "--drive", twin.url, "--config", twin.config(mode.lower(), profile),
                   "--from-here", "--duration", "0.2", "--json", "--out", f"{mode}.mcap")
    assert ran.returncode == 0, ran.stderr
    kpis = json.loads(ran.stdout)
    assert kpis["clock"] == "sim" and kpis["ticks"] == 400 and kpis["stale_feedback"] == 0
    assert kpis["rms_error_deg"] < RMS_BOUND_DEG[mode], kpis
    if mode != "CST":
        assert kpis["set_point"] == ("position" if mode == "CSP" else "velocity")
    events = {m["kind"]: m["message"] for _, m in
              read_session(str(twin.folder / f"{mode}.mcap")).topic("/events")}
    assert events["drive.clock"].startswith("drive node 1 keeps the master's time")
    return kpis, events


def move(twin: TwinFolder, window_deg: float, decelerate: bool, master: str = "") -> None:
    """``hil drive move`` 30 deg on at 90 deg/s: done (statusword bit 10) within
    ``window_deg``; ``decelerate``: the drive has a profile deceleration (0x6084); ``master``:
    more ``[master]`` keys."""
    deceleration = ("--deceleration", 360) if decelerate else ()
    moved = twin.hil("drive", "move", twin.url, "30", "--relative", "--config",
                     twin.config("pp", master), "--velocity", 90, "--acceleration", 360,
                     *deceleration, "--json", "--out", "move.mcap")
    assert moved.returncode == 0, moved.stderr
    kpis = json.loads(moved.stdout)
    assert kpis["reached"] and abs(kpis["error_deg"]) <= window_deg, (kpis, window_deg)
    assert twin.last_statusword("move.mcap") & 0x0400  # target reached


def home(twin: TwinFolder, method: int, options: tuple[object, ...], offset_deg: float,
         window_deg: float, master: str = "") -> None:
    """``hil drive home`` by ``method`` (with ``options``: speeds, acceleration, offset): done
    at the method's home point, which then reads ``offset_deg``, within ``window_deg``;
    statusword bits 12 (homing attained) and 10; ``master``: more ``[master]`` keys."""
    homed = twin.hil("drive", "home", twin.url, "--config", twin.config("hm", master), "--method",
                     method, *options, "--json", "--out", f"home{method}.mcap")
    assert homed.returncode == 0, homed.stderr
    kpis = json.loads(homed.stdout)
    assert kpis["reached"] and kpis["method"] == method, kpis
    assert abs(kpis["position_deg"] - offset_deg) <= window_deg, (kpis, window_deg)
    assert twin.last_statusword(f"home{method}.mcap") & 0x1400 == 0x1400
