"""The flags of a run on a place that are refused before any coordinator is reached."""

from __future__ import annotations

import socket

import pytest

from tests.cli import hil_here

pytestmark = [pytest.mark.lab]


@pytest.mark.parametrize("app, device", [("bench", "bench"), ("servo", "drive")])
def test_the_place_and_a_device_url_are_one_too_many(capsys, tmp_path, app, device):
    out = hil_here(capsys, app, "run", "--controller", "bc" if app == "bench" else "pid",
                   "--place", "p", f"--{device}", "emulated", cwd=tmp_path)
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
