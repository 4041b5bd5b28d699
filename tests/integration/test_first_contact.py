"""The first contact with a drive, from outside: a drive at node 4 on socketcand (what
``hil emulate drive --node 4`` serves, served in the test's process) and a run that looks for
node 1. A node that has never answered gets the SDO time-out, not the lockstep bound, and the
error names the nodes a scan of the bus found; ``hil drive scan`` takes node ids of CiA 301
only."""

from __future__ import annotations

import pytest

from tests.cli import hil_here
from tests.served_here import drive_served_here

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]

# a lockstep bound no test would sit out: a run that waited it for the first answer would time
# the test out; the SDO time-out stays the packaged 1 s
PATIENT = "[master]\nlockstep_timeout_ms = 600000\n"


@pytest.fixture(scope="module")
def node_4():
    with drive_served_here(node=4) as emulator:
        yield emulator


def test_a_wrong_node_id_fails_at_the_sdo_timeout_naming_the_nodes_there(node_4, tmp_path,
                                                                           capsys):
    config = tmp_path / "drive.toml"
    config.write_text(PATIENT)
    wrong = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", node_4.url,
                     "--config", config, "--duration", "0.1", "--out", "wrong.mcap",
                     cwd=tmp_path)
    assert wrong.returncode == 2, wrong.stderr
    line = wrong.stderr.strip()
    assert "\n" not in line and "Traceback" not in line
    assert line.startswith("hil: error: drive node 1 did not answer SDO ")
    assert "within 1 s" in line and "it has never answered" in line
    assert "the nodes that answered a scan of the bus: 4 " in line
    assert not (tmp_path / "wrong.mcap").exists()  # nothing ran
    # the same bus and config with the right node runs
    right = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive", node_4.url,
                     "--config", config, "--node", "4", "--duration", "0.1", "--out",
                     "right.mcap", cwd=tmp_path)
    assert right.returncode == 0, right.stderr


def test_an_empty_bus_is_said(tmp_path, capsys, socketcand_server):
    host, port = socketcand_server.address
    config = tmp_path / "drive.toml"
    config.write_text(PATIENT)
    run = hil_here(capsys, "servo", "run", "--controller", "pid", "--drive",
                   f"socketcand://{host}:{port}", "--config", config, "--duration", "0.1",
                   "--out", "none.mcap", cwd=tmp_path)
    assert run.returncode == 2
    assert "it has never answered; no node answered a scan of the bus" in run.stderr


@pytest.mark.parametrize("node", ["0", "128", "200"])
def test_drive_scan_refuses_a_node_id_outside_cia_301(node_4, capsys, node):
    scan = hil_here(capsys, "drive", "scan", node_4.url, "--node", node)
    assert scan.returncode == 2
    assert scan.stderr.count("\n") == 1 and "--node" in scan.stderr
    assert "node 200: unnamed" not in scan.stdout and scan.stdout == ""
