"""``hil empc build``: the figures, the documented JSON keys, the C file, one-line errors."""

from __future__ import annotations

import json

import pytest

from hil.cli.main import main

pytestmark = [pytest.mark.slow]


def test_build_prints_the_contract_keys_and_writes_c(tmp_path, capsys):
    target = tmp_path / "law.c"
    assert main(["empc", "build", "--ht", "3", "--hp", "50", "--json",
                 "--export-c", str(target)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert {"regions", "controllers", "tree_nodes", "tree_depth", "build_s"} <= set(result)
    assert (result["regions"], result["controllers"]) == (21, 11)
    assert result["tree_nodes"] == 2 * result["tree_leaves"] - 1
    assert result["build_s"] > 0 and result["c_file"] == str(target)
    assert "int empc_eval(const double theta[], double *du)" in target.read_text()


def test_box_option_changes_the_solution(capsys):
    """A box tight around the paper's scenarios: the two controllers that need a strongly
    excited resonance (u(1) at one limit, u(2) at the other) are not reached."""
    assert main(["empc", "build", "--json", "--box", "dx1=1,dx2=1,dx3=0.02,dx4=0.02,e=30,dr=1"]
                ) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["box"]["e"] == [-30.0, 30.0] and result["box"]["dx3"] == [-0.02, 0.02]
    assert (result["regions"], result["controllers"]) == (19, 9)


def test_text_output(capsys):
    assert main(["empc", "build", "--ht", "2", "--hp", "20", "--umax", "500"]) == 0
    out = capsys.readouterr().out
    assert "H_t = 2, H_u = 2, H_p = 20" in out and "|u| <= 500 mA" in out
    for key in ("regions", "controllers", "tree_nodes", "tree_depth", "build_s"):
        assert key in out


def test_bad_arguments_give_one_line_errors(tmp_path, capsys):
    cases = [
        (["--box", "speed=3"], "unknown parameter(s) speed"),
        (["--box", "u=-2000:0"], "current limits"),
        (["--ht", "1"], "first-order-hold ERT needs H_t >= 2"),
        (["--ht", "7"], "H_u <= 6"),
        (["--export-c", str(tmp_path / "no" / "x.c")], "no such directory"),
    ]
    for args, message in cases:
        assert main(["empc", "build", *args]) == 2
        err = capsys.readouterr().err
        assert err.startswith("hil: error: ") and message in err and err.count("\n") == 1


def test_too_large_control_horizon_is_refused_before_any_work(capsys):
    from hil.cli.main import main

    assert main(["servo", "run", "--controller", "empc", "--ht", "8", "--hu", "8"]) == 2
    err = capsys.readouterr().err
    assert "H_u = 8 is too large" in err and err.count("\n") == 1
