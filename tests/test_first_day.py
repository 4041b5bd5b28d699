"""What a new user met on the first day, each tried with the ``hil`` command from a folder
outside the repository: a ``hil`` process for the first case of each finding, the command line
in this process (:func:`hil_here`, from the same folder) for more cases of it."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.cli import hil_here

ROOT = Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.timeout(180)]


def hil(cwd, *args, timeout=120):
    """``hil ARGS`` as a process, from ``cwd``."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "hil", *map(str, args)], cwd=cwd,
                          capture_output=True, text=True, env=env, timeout=timeout, check=False)


def one_error_line(done: subprocess.CompletedProcess[str]) -> str:
    """The one line a refusal prints (exit 2, no traceback)."""
    assert done.returncode == 2, (done.stdout, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    return lines[0]


# -- config keys are checked as the flags are ---------------------------------------------------

@pytest.mark.parametrize(("text", "says"), [
    ("[master]\ncurrent_limit_ma = 500\n",
     "unknown key 'master.current_limit_ma' (did you mean 'master.current_limit_mA'? "),
    ("[mastr]\nnode_id = 2\n", "unknown key 'mastr' (did you mean 'master'? "),
    ("[master]\ncurrent_limit_mA = 0.3\n", "key 'master.current_limit_mA' = 0.3: 0.3 mA is "
     "below 1 mA: the value is in mA (0.3 A would be 300 mA)"),
    ("[[axis]]\nname = 'x'\nnode = 1\ncurrent_limit_mA = 0.5\n[[axis]]\nname = 'y'\nnode = 2\n",
     "key 'axis[0].current_limit_mA' = 0.5: 0.5 mA is below 1 mA"),
    ("[master]\ncurrent_limit_mA = '0.3A'\n", "key 'master.current_limit_mA' takes a number "
     "of mA, without its unit: '0.3A' is 300 (write 300)"),
    ("[safety]\nfollowing_error_ms = '2s'\n", "key 'safety.following_error_ms' takes a "
     "number of ms, without its unit: '2s' is 2000 (write 2000)"),
], ids=["typo", "table-typo", "amperes", "axis-amperes", "with-unit", "ms-with-unit"])
def test_a_config_key_is_checked_when_read_with_the_flags_rules(tmp_path, capfd, text, says):
    """A typo gets "did you mean", a current in amperes or a value written with its unit the
    words ``--umax 0.3`` and ``--duration 10ms`` get, when the file is read: before anything
    runs, and with --print-config too."""
    (tmp_path / "mine.toml").write_text(text)
    first = text.startswith("[master]\ncurrent_limit_ma")
    run = hil if first else lambda cwd, *a: hil_here(capfd, *a, cwd=cwd)
    done = run(tmp_path, "servo", "run", "--controller", "pid", "--config", "mine.toml",
               "--duration", "0.05")
    assert one_error_line(done).startswith(f"hil: error: mine.toml: {says}")
    assert not (tmp_path / "sessions").exists()  # refused before the run
    shown = hil_here(capfd, "servo", "run", "--config", "mine.toml", "--print-config",
                     cwd=tmp_path)
    assert one_error_line(shown).startswith(f"hil: error: mine.toml: {says}")


def test_a_bench_config_key_gets_did_you_mean_too(tmp_path, capfd):
    (tmp_path / "bench.toml").write_text("[relays.P1]\ndwel_s = 6\n")
    done = hil_here(capfd, "bench", "run", "--controller", "bc", "--config", "bench.toml",
                    "--print-config", cwd=tmp_path)
    assert "unknown key 'relays.P1.dwel_s' (did you mean 'relays.P1.dwell_s'? " \
        in one_error_line(done)
