"""drive.toml parsed once (hil/servo/config.py): defaults, layering, and one error line naming
the file and the key for an unknown key, a wrong type or a value out of range."""

import math

import pytest

from hil.cli.main import main
from hil.drivers.canopen import DriveMasterConfig
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.errors import ConfigError
from hil.servo.config import default_drive_text, load_drive_config


def write(tmp_path, text):
    path = tmp_path / "my-drive.toml"
    path.write_text(text)
    return path


def test_the_packaged_defaults_are_the_dataclasses_defaults():
    drive = load_drive_config()
    assert drive.master == DriveMasterConfig()
    assert drive.emulator == DriveEmulatorConfig()
    assert drive.emulator.disturbance.end_s == math.inf  # end_s omitted: no end
    assert drive.text == default_drive_text() and drive.source == "drive config"


def test_a_user_file_then_overrides_are_laid_over_the_default(tmp_path):
    path = write(tmp_path, "[master]\ncurrent_limit_mA = 750.0\nrx_timeout_us = 800\n"
                           "[emulator.disturbance]\nend_s = 2.5\n")
    drive = load_drive_config(path, overrides={"master": {"current_limit_mA": 500}})
    assert drive.master.current_limit_ma == 500.0 and drive.master.rx_timeout_s == 800e-6
    assert drive.master.node_id == 1  # untouched keys keep the default
    assert drive.emulator.disturbance.end_s == 2.5
    assert drive.source == str(path) and drive.text == path.read_text()
    assert drive.data["master"]["current_limit_mA"] == 500  # what the session records
    again = drive.laid_over({"master": {"mode": "csp"}})
    assert again.master.mode == "csp" and again.master.current_limit_ma == 500.0
    with pytest.raises(ConfigError, match=rf"^{path}: key 'master\.mode'"):
        drive.laid_over({"master": {"mode": "velocity"}})


@pytest.mark.parametrize(("toml", "message"), [
    ("[master]\nnode_idd = 2\n", "unknown key 'master.node_idd'"),
    ("[emulator.friction]\nviscous = 1.0\n", "unknown key 'emulator.friction.viscous'"),
    ("[masterr]\nnode_id = 2\n", "unknown key 'masterr'"),
    ("[master]\nstale_cycles = 2.5\n",
     "key 'master.stale_cycles' must be an integer, got a number 2.5"),
    ("[bus]\nbitrate = true\n", "key 'bus.bitrate' must be an integer, got a boolean true"),
    ("[emulator]\nchannel = 3\n", "key 'emulator.channel' must be a string, got an integer 3"),
    ("[master]\nnode_id = 128\n", "key 'master.node_id' must be <= 127, got 128"),
    # found by the fuzz campaign: taken, then a struct.error writing 0x1006 (32 bits)
    ("[master]\ncycle_period_us = 4294967296\n",
     "key 'master.cycle_period_us' must be <= 4294967295 us, got 4294967296 us"),
    ("[master]\ncurrent_limit_mA = 0\n", "key 'master.current_limit_mA' must be > 0 mA, got 0 mA"),
    # found by the fuzz campaign: a friction that pushes the axis ran it to inf (internal errors)
    ("[emulator.friction]\nviscous_mA_per_deg_s = -747\n",
     "key 'emulator.friction.viscous_mA_per_deg_s' must be >= 0 mA/(deg/s), got -747 mA/(deg/s)"),
    # and a friction too steep for the plant's period: it ran away the same way
    ("[emulator.friction]\nviscous_mA_per_deg_s = 1498\n",
     "key 'emulator.friction' makes the axis run away: its slope at standstill, "
     "viscous_mA_per_deg_s + coulomb_mA / coulomb_smoothing_deg_s = 1498 mA/(deg/s), grows it "
     "2.786 times per 500 us period (at most 1.001)"),
    ("[master]\nquick_stop_option = 3\n",
     "key 'master.quick_stop_option' must be one of 0, 1, 2, 5, 6, got 3"),
    ("[emulator.disturbance]\nend_s = inf\n",
     "key 'emulator.disturbance.end_s' must be a finite number, got inf"),
    ("[bus]\nchannel = \"\"\n", "key 'bus.channel' must be a bus name"),
])
def test_a_bad_key_is_one_error_naming_the_file_and_the_key(tmp_path, toml, message):
    path = write(tmp_path, toml)
    with pytest.raises(ConfigError) as error:
        load_drive_config(path)
    assert str(error.value).startswith(f"{path}: ")
    assert message in str(error.value)
    assert "\n" not in str(error.value)


def test_servo_run_with_a_bad_config_prints_one_error_line_and_exits_2(tmp_path, capsys):
    path = write(tmp_path, "[master]\nheartbeat_period_ms = -5\n")
    out = tmp_path / "never.mcap"
    code = main(["servo", "run", "--controller", "pid", "--config", str(path), "--out",
                 str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err == (f"hil: error: {path}: key 'master.heartbeat_period_ms' must be >= 0 ms, "
                   "got -5 ms\n")
    assert not out.exists()


def test_mpc_prediction_is_decimated_in_real_time_and_in_long_lockstep_runs():
    """The period of /mpc/prediction, from the options alone (no loop runs)."""
    from hil.servo.options import ServoRunOptions
    from hil.servo.task import PREDICTION_EVERY_REALTIME, PREDICTION_EVERY_TICK_UP_TO_S

    def every(**kw):
        return ServoRunOptions(controller="mpc", **kw).prediction_period

    assert every(duration_s=PREDICTION_EVERY_TICK_UP_TO_S) == 1  # a short lockstep run: all
    assert every(duration_s=PREDICTION_EVERY_TICK_UP_TO_S + 1) == PREDICTION_EVERY_REALTIME
    assert every(duration_s=2, realtime=True) == PREDICTION_EVERY_REALTIME
    assert every(duration_s=3600, prediction_every=1) == 1  # asked for: every tick
