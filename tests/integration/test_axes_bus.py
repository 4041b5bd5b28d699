"""Several axes on a real bus, from the command line as a user runs it (a folder outside the
repository): the plan and the refusal give one figure, every way out the plan names can be
taken (a longer cycle, one TPDO per axis, a second bus: each run against hil's drive emulator
on socketcand, three axes' a `hil emulate drive` process, the others' served in the test's
process), the warning of the emulated bus is on the terminal, and a bit rate
classic CAN cannot carry is refused unless the bus is CAN FD. Each command and flag runs from
outside at least once; its other cases run ``main`` in this process, in the same folder
(``hil_here``: the same exit status and output, without a second of interpreter start)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil import api
from hil.core.recording.reader import read_session
from tests.cli import hil_here as in_process
from tests.served_here import drive_served_here

ROOT = Path(__file__).resolve().parents[2]
FIGURE = "(worst case: every frame with all the stuff bits it can take)"


def hil(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, capture_output=True,
                          text=True, env=dict(os.environ, PYTHONPATH=str(ROOT)), timeout=300)


def hil_here(cwd, capsys, *args):
    """``hil ARGS`` run by ``main`` in this process from ``cwd``, as :func:`hil` reports it."""
    return in_process(capsys, *args, cwd=cwd)


def config(folder: Path, name: str, text: str) -> str:
    path = folder / name
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize("drive_toml, axes, outside", [
    ("", 2, True),                                      # 2 axes at 2 kHz: 706 us
    ('[master]\ntpdo_layout = "one"\n', 2, False),      # one TPDO each: 516 us
    ("[bus]\nbitrate = 500000\n", 2, False),            # half the bit rate: twice the time
    ("[master]\ncycle_period_us = 1000\n", 3, False),   # 3 axes at 1 kHz: 1033 us
])
@pytest.mark.slow  # a second or more: make test runs it, make check does not
def test_the_plan_and_the_refusal_give_one_figure(tmp_path, capsys, drive_toml, axes, outside):
    """The first case's plan and refusal from outside (``outside``), the others in this
    process; the plan's text, the same command without --json, in this process."""

    def hil_as_set(*args: str) -> subprocess.CompletedProcess[str]:
        return hil(tmp_path, *args) if outside else hil_here(tmp_path, capsys, *args)

    path = config(tmp_path, "drive.toml", drive_toml)
    planned = hil_as_set("drive", "plan", "--axes", str(axes), "--config", path, "--json")
    assert planned.returncode == 1, planned.stderr
    plan = json.loads(planned.stdout)
    assert plan["bus_time"] == FIGURE[1:-1] and plan["bus_time_us"] > plan["period_us"]
    names = ",".join(f"{name}={node}" for node, name in enumerate("xyz"[:axes], start=1))
    refused = hil_as_set("servo", "run", "--axes", names, "--controller", "mpc",
                         "--config", path, "--drive", "virtual://one-figure", "--out", "no.mcap")
    assert refused.returncode == 2 and not (tmp_path / "no.mcap").exists()
    figure = f"{axes} axes need {plan['bus_time_us']:.0f} us of bus time per cycle"
    said = plan["problem"].partition("; ways out")[0]
    assert said.startswith(figure) and FIGURE in said
    assert refused.stderr.startswith(f"hil: error: the bus plan does not fit "
                                     f"(virtual://one-figure): {said}; ways out: ")
    text = hil_here(tmp_path, capsys, "drive", "plan", "--axes", str(axes), "--config", path)
    assert f"bus time per cycle {plan['bus_time_us']:.0f} us {FIGURE}" in text.stdout
    assert f"does not fit: {said}" in text.stdout


@pytest.mark.slow  # a process of its own: make test runs it, make check does not
def test_the_emulated_bus_warns_on_the_terminal(tmp_path):
    done = hil(tmp_path, "servo", "run", "--axes", "x=1,y=2", "--controller", "pid",
               "--duration", "0.02", "--out", "warned.mcap", "--quiet")
    assert done.returncode == 0, done.stderr
    warning = [line for line in done.stderr.splitlines() if line.startswith("hil: warning:")]
    assert len(warning) == 1
    assert warning[0].startswith("hil: warning: on a real bus this would not fit: 2 axes need "
                                 f"706 us of bus time per cycle at 1000000 bit/s {FIGURE}")
    events = [m for _, m in read_session(tmp_path / "warned.mcap").topic("/events")
              if m["kind"] == "bus.plan"]
    assert [f"hil: warning: {m['message']}" for m in events] == warning


def test_empc_at_1000_us_is_refused_naming_it(tmp_path, capsys):
    path = config(tmp_path, "slow.toml", "[master]\ncycle_period_us = 1000\n")
    done = hil_here(tmp_path, capsys, "servo", "run", "--controller", "empc", "--config", path,
                    "--out", "empc.mcap")
    assert done.returncode == 2 and not (tmp_path / "empc.mcap").exists()
    assert done.stderr == ("hil: error: controller 'empc' does not run at a cycle period of "
                           "1000 us (master.cycle_period_us): it runs at 500 us\n")
    odd = config(tmp_path, "odd.toml", "[master]\ncycle_period_us = 750\n")
    done = hil_here(tmp_path, capsys, "servo", "run", "--controller", "mpc", "--config", odd,
                    "--out", "odd.mcap")
    assert done.returncode == 2
    assert "key 'master.cycle_period_us' is 750 us: the emulated drive steps its axis every " \
           "500 us" in done.stderr


@pytest.mark.slow  # a process of its own: make test runs it, make check does not
def test_a_bitrate_above_1_mbit_is_refused_unless_the_bus_is_can_fd(tmp_path, capsys):
    def here(*args: str) -> subprocess.CompletedProcess[str]:
        return hil_here(tmp_path, capsys, *args)

    classic = config(tmp_path, "classic.toml", "[bus]\nbitrate = 2000000\n")
    refused = here("servo", "run", "--print-config", "--config", classic)
    assert refused.returncode == 2
    assert refused.stderr == (
        f"hil: error: {classic}: key 'bus.bitrate' is 2000000 bit/s: classic CAN stops at "
        "1000000 bit/s (1 Mbit/s); above it only on a CAN FD bus: fd = true in [bus.options] "
        "(or ?fd=true in a bus URL)\n")
    flag = hil(tmp_path, "drive", "plan", "--bitrate", "2000000")
    assert flag.returncode == 2
    assert flag.stderr.startswith("hil: error: --bitrate 2000000 bit/s: classic CAN stops at "
                                  "1000000 bit/s")
    url = here("servo", "run", "--print-config", "--drive", "virtual://fast?bitrate=2000000")
    assert url.returncode == 2
    assert "virtual://fast?bitrate=2000000: bitrate 2000000 bit/s: classic CAN" in url.stderr
    fd = config(tmp_path, "fd.toml", '[bus]\ninterface = "virtual"\nchannel = "fd"\n'
                "bitrate = 2000000\n[bus.options]\nfd = true\n")
    accepted = here("servo", "run", "--print-config", "--json", "--config", fd)
    assert accepted.returncode == 0, accepted.stderr
    assert json.loads(accepted.stdout)["bus.bitrate"]["value"] == 2_000_000
    planned = here("drive", "plan", "--axes", "2", "--config", fd, "--json")
    assert planned.returncode == 0  # 2 axes fit 2 kHz at 2 Mbit/s
    assert json.loads(planned.stdout)["bitrate"] == 2_000_000


def test_an_axis_on_a_bus_of_its_own_in_the_drive_config(tmp_path, capsys):
    axes = '[[axis]]\nname = "x"\nnode = 1\n\n[[axis]]\nname = "y"\nnode = 1\n'
    path = config(tmp_path, "axes.toml", axes + 'bus = "socketcand://127.0.0.1:29536"\n')
    # in this process: --print-config runs from outside in tests/integration/
    # test_configured_runs.py, --config in test_the_plan_and_the_refusal_give_one_figure
    shown = hil_here(tmp_path, capsys, "servo", "run", "--print-config", "--json", "--config",
                     path)
    assert shown.returncode == 0, shown.stderr
    assert json.loads(shown.stdout)["axis"]["value"][1]["bus"] == \
        "socketcand://127.0.0.1:29536"
    for body, problem in ((axes, "[[axis]]: a node given twice on one bus (node 1)"),
                          (axes + 'bus = "socketcan://"\n',
                           "key 'axis[1].bus' is not a bus URL: drive 'socketcan://': no "
                           "channel")):
        bad = hil_here(tmp_path, capsys, "servo", "run", "--print-config", "--config",
                       config(tmp_path, "bad.toml", body))
        assert bad.returncode == 2 and problem in bad.stderr, bad.stderr


def axes_run(tmp_path: Path, out: str, capsys: pytest.CaptureFixture[str], *args: str) -> dict:
    """The KPIs of a 0.5 s run, by ``main`` in this process (``servo run --axes`` runs from
    outside in :func:`test_the_emulated_bus_warns_on_the_terminal`)."""
    argv = ("servo", "run", *args, "--duration", "0.5", "--out", out, "--json")
    done = hil_here(tmp_path, capsys, *argv)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def tracking(kpis: dict, names: tuple[str, ...], ticks: int, bound_deg: float) -> None:
    """Every axis ran every tick on fresh feedback and followed its reference."""
    assert set(kpis["axes"]) == set(names) and kpis["ticks"] == kpis["sync_cycles"] == ticks
    for axis in kpis["axes"].values():
        assert axis["stale_feedback"] == 0 and axis["late_frames"] == 0
        assert 0 < axis["max_error_deg"] < bound_deg


@pytest.mark.slow
def test_a_longer_cycle_with_pid_takes_two_axes_onto_one_bus(tmp_path, capsys):
    slow = config(tmp_path, "slow.toml", "[master]\ncycle_period_us = 1000\n")
    with drive_served_here(node=[1, 2]) as drive:
        refused = hil_here(tmp_path, capsys, "servo", "run", "--axes", "x=1,y=2", "--controller",
                           "pid", "--drive", drive.url, "--out", "no.mcap")
        unstable = hil_here(tmp_path, capsys, "servo", "run", "--axes", "x=1,y=2",
                            "--controller", "pid", "--drive", drive.url, "--config", slow,
                            "--out", "no.mcap")
        kpis = axes_run(tmp_path, "slow.mcap", capsys, "--axes", "x=1,y=2", "--controller",
                        "pid", "--param", "ti_us=8000", "--drive", drive.url, "--config", slow)
    assert refused.returncode == 2
    assert "master.cycle_period_us >= 707 (1415 Hz or slower; controller 'pid' runs at " \
           "1000 us)" in refused.stderr
    assert unstable.returncode == 2 and "--param ti_us=8000" in unstable.stderr
    # 500 ticks of 1 ms: the PID follows the 2 deg sine as it does at 500 us (0.53 deg)
    tracking(kpis, ("x", "y"), 500, 0.6)
    feedback = [m for _, m in read_session(tmp_path / "slow.mcap").topic("/axis/x/feedback")]
    assert len(feedback) == 500


@pytest.mark.slow
def test_one_tpdo_per_axis_takes_three_axes_onto_one_bus_at_1_khz(tmp_path, capsys):
    two = config(tmp_path, "two.toml", "[master]\ncycle_period_us = 1000\n")
    one = config(tmp_path, "one.toml", '[master]\ncycle_period_us = 1000\ntpdo_layout = "one"\n')
    with api.start_drive_emulator(node=[1, 2, 3]) as drive:
        refused = hil_here(tmp_path, capsys, "servo", "run", "--axes", "x=1,y=2,z=3",
                           "--controller", "mpc", "--drive", drive.url, "--config", two,
                           "--out", "no.mcap")
        kpis = axes_run(tmp_path, "one.mcap", capsys, "--axes", "x=1,y=2,z=3", "--controller",
                        "mpc", "--drive", drive.url, "--config", one)
    assert refused.returncode == 2
    assert 'master.tpdo_layout = "one"' in refused.stderr and "748 us, fits" in refused.stderr
    tracking(kpis, ("x", "y", "z"), 500, 0.1)
    data = read_session(tmp_path / "one.mcap")
    velocities = [m["velocity_deg_s"] for _, m in data.topic("/axis/z/feedback")]
    assert max(abs(v) for v in velocities) > 5.0  # derived from the position, tick by tick


@pytest.mark.slow
def test_a_second_bus_takes_two_axes_at_2_khz(tmp_path, capsys):
    with drive_served_here() as first, drive_served_here() as second:
        kpis = axes_run(tmp_path, "buses.mcap", capsys, "--axes",
                        f"x=1@{first.url},y=1@{second.url}", "--controller", "pid")
    tracking(kpis, ("x", "y"), 1000, 0.6)
    assert [kpis["axes"][name]["bus"] for name in ("x", "y")] == \
        [f"{first.url}/can0", f"{second.url}/can0"]
    assert kpis["buses"] == [f"{first.url}/can0", f"{second.url}/can0"]
    data = read_session(tmp_path / "buses.mcap")
    cycles = {name: [m["cycle"] for _, m in data.topic(f"/axis/{name}/feedback")]
              for name in ("x", "y")}
    assert cycles["x"] == cycles["y"] and len(cycles["x"]) == 1000  # a SYNC on each, each tick
    plans = json.loads(data.metadata["bus_plan"]["json"])["buses"]
    assert [(p["axis_names"], p["fits"]) for p in plans] == [(["x"], True), (["y"], True)]
