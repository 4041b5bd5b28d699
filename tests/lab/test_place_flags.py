"""The flags of a run on a place that are refused before any coordinator is reached, and the
labgrid configs of the shared benches guide as labgrid reads them."""

from __future__ import annotations

import socket

import pytest

from tests.cli import hil_here
from tests.docs import blocks, page

pytestmark = [pytest.mark.lab]


@pytest.mark.parametrize("command, device", [
    (["bench", "run", "--controller", "bc"], "bench"),
    (["servo", "run", "--controller", "pid"], "drive"),
    (["bench", "identify"], "bench"),
    (["servo", "identify"], "drive"),
    (["sweep", "servo", "--controller", "pid", "--serial", "--grid", "param.kp=1"], "drive")],
    ids=["bench-run", "servo-run", "bench-identify", "servo-identify", "sweep-servo"])
def test_the_place_and_a_device_url_are_one_too_many(capsys, tmp_path, command, device):
    out = hil_here(capsys, *command, "--place", "p", f"--{device}", "emulated", cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip() == (f"hil: error: --place p and --{device} both say where the "
                                  f"{device} is: give one")


@pytest.mark.parametrize("flag", [["--coordinator", "127.0.0.1:20408"], ["--wait", "5"]])
def test_coordinator_and_wait_go_with_a_place(capsys, tmp_path, flag):
    out = hil_here(capsys, "bench", "run", "--controller", "bc", *flag, cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip() == f"hil: error: {flag[0]} goes with --place NAME"


def test_a_coordinator_that_does_not_answer_is_one_line(capsys, tmp_path):
    with socket.socket() as closed:  # a free port nobody listens on
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    out = hil_here(capsys, "servo", "run", "--controller", "pid", "--place", "p",
                   "--coordinator", f"127.0.0.1:{port}", cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip() == (f"hil: error: --coordinator 127.0.0.1:{port}: no labgrid "
                                  "coordinator answers there")


def test_a_negative_wait_is_refused_by_the_parser(capsys, tmp_path):
    out = hil_here(capsys, "bench", "run", "--controller", "bc", "--place", "p", "--wait", "-1",
                   cwd=tmp_path)
    assert out.returncode == 2 and "expected seconds >= 0, got -1" in out.stderr


def readme_yaml() -> list[str]:
    return blocks(page("guides/shared-benches.md"), "yaml")[:2]


def test_the_guides_exporter_config_and_environment_are_what_labgrid_reads(tmp_path):
    """The guide's exporter config, read as labgrid's exporter reads it (a Jinja template),
    makes the hil resources; its environment imports hil.lab and holds a RemotePlace."""
    from labgrid.config import Config
    from labgrid.remote.config import ResourceConfig

    from hil.lab import HilBench, HilDrive

    exporter, env = readme_yaml()
    (tmp_path / "exporter.yaml").write_text(exporter)
    groups = ResourceConfig(str(tmp_path / "exporter.yaml")).data
    bench = HilBench(None, "b", **groups["bench-1"]["HilBench"])
    drive = HilDrive(None, "d", **groups["drive-1"]["HilDrive"])
    assert bench.url.startswith("modbus-tcp://") and drive.node == 1
    (tmp_path / "env.yaml").write_text(env)
    config = Config(str(tmp_path / "env.yaml"))
    assert config.get_imports() == ["hil.lab"]
    main = config.get_targets()["main"]
    assert "RemotePlace" in main["resources"]
    assert set(main["drivers"]) == {"HilBenchDriver", "HilDriveDriver"}


def test_a_sweep_on_a_place_runs_its_trials_one_after_another_on_its_device(capsys, tmp_path):
    """A place's device is one device: no parallel trials, no swept device URL (both refused
    before any coordinator is reached or the place is held)."""
    sweep = ("sweep", "servo", "--controller", "pid", "--place", "p")
    out = hil_here(capsys, *sweep, "--grid", "param.kp=1,2", cwd=tmp_path)
    assert out.returncode == 2
    assert out.stderr.strip() == ("hil: error: --place p: a place's drive is one device; add "
                                  "--serial to run the trials one after another")
    with socket.socket() as closed:  # a free port nobody listens on
        closed.bind(("127.0.0.1", 0))
        port = closed.getsockname()[1]
    out = hil_here(capsys, *sweep, "--serial", "--grid", "param.kp=1,2", "--coordinator",
                   f"127.0.0.1:{port}", cwd=tmp_path)
    assert out.returncode == 2 and "no labgrid coordinator answers there" in out.stderr
