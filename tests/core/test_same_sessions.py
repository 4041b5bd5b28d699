"""Restructuring the run must not change what a run does: short lockstep runs of both
applications (`tests/session_digest.py`: the EEC and BC on the bench, MPC, PID and a
disturbance on the servo, limits included) give, bit for bit, the messages and KPIs recorded in
`tests/data/session_digests.json` by the code before the run pipeline and the tick phases
(commit 0377251). Wall-clock fields (step and solve times, loop timing) are left out. Since,
on purpose: the servo runs' ``drive.configured`` event carries the drive's scaling;
the bench runs' ``faults`` KPI counts ``bad_readings`` (0 here) and the servo runs
have ``peak_requested_mA`` (equal to ``peak_current_mA``, nothing clamped); every other
message and every KPI is still the one of 0377251.

The reference holds for OpenBLAS's AVX2 kernel (``REFERENCE_BLAS_KERNEL``): on a CPU where
OpenBLAS picks another (AVX-512 on recent Intel and AMD CPUs), the runs are made in a child
process that asks OpenBLAS for the reference's kernel."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.session_digest import EXPERIMENTS, REFERENCE_BLAS_KERNEL, blas_kernel, record

pytestmark = [pytest.mark.slow]

REFERENCE = json.loads((Path(__file__).parents[1] / "data" / "session_digests.json").read_text())
ROOT = Path(__file__).parents[2]
#: a child process's environment: OpenBLAS's reference kernel, the repository importable
REFERENCE_KERNEL_ENV = {**os.environ, "OPENBLAS_CORETYPE": REFERENCE_BLAS_KERNEL,
                        "PYTHONPATH": str(ROOT)}


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_a_lockstep_run_records_what_it_recorded_before(tmp_path, name):
    now = record_with_reference_kernel(tmp_path, name)
    before = REFERENCE[name]
    assert now["kpis"] == before["kpis"]
    assert now["topics"] == before["topics"]


def test_the_digest_sees_a_changed_message(tmp_path):
    from hil import api
    from tests.session_digest import session_digest

    out_a, out_b = str(tmp_path / "a.mcap"), str(tmp_path / "b.mcap")
    api.run_servo("pid", reference="sine:amplitude=2,frequency=1", duration_s=0.05, out=out_a)
    api.run_servo("pid", reference="sine:amplitude=2.000001,frequency=1", duration_s=0.05,
                  out=out_b)
    a, b = session_digest(out_a), session_digest(out_b)
    assert a["/drive/command"]["count"] == b["/drive/command"]["count"] == 100
    assert a["/drive/command"]["sha256"] != b["/drive/command"]["sha256"]
    assert a == session_digest(out_a)  # and the same file gives the same digest


def record_with_reference_kernel(tmp_path: Path, name: str) -> dict:
    """The experiment's digests with OpenBLAS's reference kernel: here if this process has it,
    else in a child process told to use it (a CPU without AVX2 cannot: the test is skipped)."""
    if blas_kernel() == REFERENCE_BLAS_KERNEL:
        return record(str(tmp_path), [name])[name]
    skip_without_avx2()
    out = tmp_path / "digests.json"
    subprocess.run([sys.executable, str(ROOT / "tests" / "session_digest.py"), "record", str(out),
                    name], env=REFERENCE_KERNEL_ENV, check=True, timeout=120)
    return json.loads(out.read_text())[name]


def test_the_reference_kernel_can_be_asked_for(tmp_path):
    """The child process really runs on the reference's kernel (else the comparison above
    would test nothing on a CPU with another one)."""
    skip_without_avx2()
    code = "from tests.session_digest import blas_kernel; print(blas_kernel())"
    kernel = subprocess.run([sys.executable, "-c", code], env=REFERENCE_KERNEL_ENV,
                            capture_output=True, text=True, check=True, timeout=60).stdout.strip()
    assert kernel == REFERENCE_BLAS_KERNEL


def skip_without_avx2() -> None:
    flags = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""
    if not {"avx2", "fma"} <= set(flags.split()):
        pytest.skip(f"the reference digests need OpenBLAS's {REFERENCE_BLAS_KERNEL} kernel "
                    f"(AVX2 and FMA), which this CPU has not (OpenBLAS: {blas_kernel()})")
