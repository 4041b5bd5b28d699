"""A user's tests with labgrid's pytest plugin (``--lg-env``): hil's ``hil_bench`` and
``hil_drive`` fixtures and the HilBenchDriver / HilDriveDriver of the environment's target, on
a place of a real coordinator and exporter (tests/lab/conftest.py)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.lab.conftest import user_env

pytestmark = [pytest.mark.lab, pytest.mark.slow]

ENV_YAML = """\
targets:
  main:
    resources:
      RemotePlace:
        name: PLACE
    drivers:
      HilBenchDriver: {}
      HilDriveDriver: {}
imports:
  - hil.lab
"""

USER_TESTS = '''
import os

from hil.protocols.cia402 import OPERATION_ENABLED, state_of


def test_the_bench_driver_opens_the_place_s_bench_behind_the_safety_layer(target):
    driver = target.get_driver("HilBenchDriver")
    assert driver.bench.read_levels()["q1"] > 0
    target.deactivate(driver)


def test_the_drive_driver_opens_the_place_s_drive_not_enabled(target):
    driver = target.get_driver("HilDriveDriver")
    assert state_of(driver.master.sdo.read_int(0x6041, 0, "<H")) != OPERATION_ENABLED
    target.deactivate(driver)


def test_hil_bench_is_the_place_s_bench(hil_bench):
    assert hil_bench.url == os.environ["BENCH_URL"] and not hil_bench.emulated
    kpis = hil_bench.run("bc", cycles=1, realtime=False)
    assert kpis["J2_VA"] > 0


def test_hil_drive_is_the_place_s_drive(hil_drive):
    assert hil_drive.url == os.environ["DRIVE_URL"] and not hil_drive.emulated
    kpis = hil_drive.run("pid", duration_s=0.2, realtime=False)
    assert kpis["rms_error_deg"] >= 0
'''


def test_a_users_tests_run_on_a_place_with_lg_env(lab, tmp_path):
    place = lab.place("bench-1", "drive-1")
    lab.acquire(place)
    folder = tmp_path / "my_lab"
    folder.mkdir()
    (folder / "env.yaml").write_text(ENV_YAML.replace("PLACE", place))
    (folder / "test_on_the_place.py").write_text(USER_TESTS)
    out = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir",
         str(folder), "--lg-env", "env.yaml", "--lg-coordinator", lab.address],
        cwd=folder, env=user_env(BENCH_URL=lab.bench_url, DRIVE_URL=lab.drive_url),
        capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "4 passed" in out.stdout
    assert lab.holder(place) is not None  # the user's, as labgrid leaves it
