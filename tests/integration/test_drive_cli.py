"""``hil emulate drive``: bad arguments and configs give one clear line, not a traceback."""

import socket

import pytest

from hil.cli.main import main

pytestmark = [pytest.mark.slow]


def run(argv, capsys):
    code = main(argv)
    return code, capsys.readouterr().err


@pytest.mark.parametrize(("toml", "needle"), [
    ("[emulator]\nquick_stop_option = 3\n", "emulator.quick_stop_option"),
    ("[emulator]\nincrements_per_rev = 1\n", "emulator.increments_per_rev"),
    ("[emulator]\ncurrent_limit_mA = \"lots\"\n", "emulator.current_limit_mA"),
    ("[emulator]\ncurent_limit_mA = 1.0\n", "unknown key 'emulator.curent_limit_mA'"),
    ("[emulator.friction]\ncoulomb = 1.0\n", "unknown key 'emulator.friction.coulomb'"),
    ("[emulator\n", "invalid TOML"),
])
def test_bad_config_is_one_error_line(tmp_path, capsys, toml, needle):
    config = tmp_path / "drive.toml"
    config.write_text(toml)
    code, err = run(["emulate", "drive", "--socketcand", "127.0.0.1:0", "--config",
                     str(config)], capsys)
    assert code == 2 and err.startswith("hil: error:") and needle in err
    assert "Traceback" not in err and err.count("\n") == 1


def test_missing_config_file_and_bad_node_are_errors(tmp_path, capsys):
    code, err = run(["emulate", "drive", "--socketcand", "127.0.0.1:0", "--config",
                     str(tmp_path / "nope.toml")], capsys)
    assert code == 2 and "config file not found" in err
    code, err = run(["emulate", "drive", "--socketcand", "127.0.0.1:0", "--node", "128"], capsys)
    assert code == 2 and "1..127" in err


def test_a_port_in_use_is_an_error(capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        code, err = run(["emulate", "drive", "--socketcand", f"127.0.0.1:{port}"], capsys)
    assert code == 2 and f"cannot listen on 127.0.0.1:{port}" in err
