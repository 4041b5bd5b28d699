"""``hil compare`` and the ``hil_baseline`` fixture, tried as a user would: lockstep servo
sessions recorded once per module in a folder outside the repository (the first by a ``hil``
process, the repository not on PYTHONPATH), then compared (by a ``hil`` process first, the
variants by the command line in this process); the alignment and the tube on their own on
made-up tick grids."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hil.compare.alignment import Series, interpolated, tick_for_tick
from hil.compare.judge import judge_signal
from hil.compare.tolerances import parse_tolerance
from tests.cli import NOT_A_USERS_PLUGINS, hil_here, hil_in

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]

ENV = {key: value for key, value in os.environ.items() if key != "PYTHONPATH"}
POSITION = "/drive/feedback:position_deg"
PD = textwrap.dedent("""
    import os

    class Pd:
        def __init__(self, reference, params):
            self.reference = reference
            self.kp = float(params.get("kp", os.environ.get("KP", 300.0)))
            self.last = None

        def step(self, position_deg, t_s):
            error = float(self.reference.position(t_s)) - position_deg
            rate = 0.0 if self.last is None else (error - self.last[1]) / (t_s - self.last[0])
            self.last = (t_s, error)
            return self.kp * error + 6.0 * rate
""")


def start(cwd: Path, *args: str, **env: str) -> subprocess.Popen[str]:
    return subprocess.Popen([sys.executable, "-m", "hil", *args], cwd=cwd, text=True,
                            env={**ENV, **env}, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE)


def hil(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "hil", *args], cwd=cwd, env=ENV,
                          capture_output=True, text=True, timeout=120, check=False)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """base.mcap (a split series: base_000.mcap...) and again.mcap, the same PD (lockstep,
    0.5 s); stiffer.mcap, its kp 250 instead of 300. base.mcap by a ``hil`` process, the other
    two by the command line in this process meanwhile (a process start costs CPU; that a
    process and this one record the same session is part of what the exact comparison of
    base and again holds)."""
    here = tmp_path_factory.mktemp("sessions")
    (here / "my_controllers.py").write_text(PD)

    def servo_run(name: str, kp: int, *split: str) -> list[str]:
        return ["servo", "run", "--controller", "my_controllers.py:Pd", "--param", f"kp={kp}",
                "--duration", "0.5", "--out", f"{name}.mcap", "--quiet", *split]

    base = start(here, *servo_run("base", 300, "--split-duration", "0.25"))
    for name, kp in (("again", 300), ("stiffer", 250)):
        assert hil_in(here, *servo_run(name, kp)) == 0, name
    _, err = base.communicate(timeout=120)
    assert base.returncode == 0, err
    return here


def test_identical_lockstep_sessions_are_within_exact_tolerance(folder):
    done = hil(folder, "compare", "base.mcap", "again.mcap", "--signal", POSITION,
               "--signal", "/drive/command:command_mA", "--json")
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["passed"] and result["alignment"] == "lockstep"
    assert result["application"] == "servo" and result["notes"] == []
    kinds = {row["kind"] for row in result["rows"]}
    assert kinds == {"kpi", "signal"} and len(result["rows"]) > 10
    assert all(row["difference"] == 0 and row["tolerance"] == "exact" and row["passed"]
               for row in result["rows"])
    names = [row["name"] for row in result["rows"]]
    assert "rms_error_deg" in names and "faults.emcy" in names
    assert "wall_s" not in names and "step_us.p99" not in names  # they time the computer
    assert done.stderr.strip().splitlines() == ["hil: within tolerance: "
                                                f"{len(names)} KPI(s) and signal(s)"]


def test_a_changed_gain_is_outside_naming_the_signal_and_its_time(folder, capsys):
    done = hil_here(capsys, "compare", "base.mcap", "stiffer.mcap", "--signal", POSITION,
                    cwd=folder)
    assert done.returncode == 1, done.stderr
    [line] = done.stderr.strip().splitlines()
    assert line.startswith("hil: outside tolerance (") and f"{POSITION} by " in line
    row = next(r for r in done.stdout.splitlines() if POSITION in r)
    assert row.endswith("FAIL")
    as_json = json.loads(hil_here(capsys, "compare", "base.mcap", "stiffer.mcap", "--signal",
                                  POSITION, "--json", cwd=folder).stdout)
    worst = next(r for r in as_json["rows"] if r["name"] == POSITION)
    assert not as_json["passed"] and not worst["passed"] and worst["difference"] > 0
    assert worst["difference"] == pytest.approx(abs(worst["candidate"] - worst["baseline"]))
    assert 0 < worst["worst_t_s"] < 0.5
    assert f"at t = {worst['worst_t_s']:.4f} s" in line and f"{worst['worst_t_s']:.4f}" in row
    assert set(as_json["origins_ns"]) == {"baseline", "candidate"}


def test_a_comparison_as_one_html_page(folder, capsys):
    done = hil_here(capsys, "compare", "base.mcap", "stiffer.mcap", "--signal", POSITION,
                    "--json", "--html", "pages/compare.html", "--max-points", "300",
                    cwd=folder)
    document = json.loads(done.stdout)
    page = (folder / "pages" / "compare.html").read_text()
    assert document["html"] == "pages/compare.html" and not document["passed"]
    worst = next(r for r in document["rows"] if r["name"] == POSITION)
    assert "FAILED" in page and POSITION in page and "<script src" not in page
    assert "worst: difference" in page and worst["worst_t_s"] > 0
    assert "Decimated for size" in page  # 1000 ticks drawn with at most 300 points
    refused = hil_here(capsys, "compare", "base.mcap", "again.mcap", "--max-points", "300",
                       cwd=folder)
    assert refused.returncode == 2 and "needs --html" in refused.stderr


def test_flags_win_over_the_tolerances_file(folder, capsys):
    (folder / "tolerances.toml").write_text(f'"{POSITION}" = "abs:0"\n"*" = "rel:50%"\n')
    loose = f"{POSITION}=tube:1,2ms"
    done = hil_here(capsys, "compare", "base.mcap", "stiffer.mcap", "--tolerances",
                    "tolerances.toml", "--tolerance", loose, "--json", cwd=folder)
    assert done.returncode == 0, done.stderr
    rows = {row["name"]: row for row in json.loads(done.stdout)["rows"]}
    assert rows[POSITION]["tolerance"] == "tube 1 deg +-2 ms"   # the flag, naming the signal
    assert rows["rms_error_deg"]["tolerance"] == "rel 50%"       # the file's default
    strict = hil_here(capsys, "compare", "base.mcap", "stiffer.mcap", "--tolerances",
                      "tolerances.toml", cwd=folder)
    assert strict.returncode == 1 and POSITION in strict.stderr


@pytest.mark.parametrize(("args", "why"), [
    (["--signal", "/drive/feedback:torque"], "signal /drive/feedback:torque: the baseline's "
     "/drive/feedback has no field torque"),
    (["--signal", "/nope:x"], "signal /nope:x: the baseline has no topic /nope"),
    (["--tolerance", "J2_VA=exact"], "KPI J2_VA: not in either session"),
    (["--tolerance", f"{POSITION}=rel:2"], "a relative tolerance is in percent"),
    (["--tolerance", f"{POSITION}=tube:0.1,2"], "a tube's lag needs its unit, ms or s"),
])
def test_what_cannot_be_compared_is_one_line_and_exit_2(folder, capsys, args, why):
    done = hil_here(capsys, "compare", "base.mcap", "again.mcap", *args, cwd=folder)
    assert done.returncode == 2
    [line] = done.stderr.strip().splitlines()
    assert why in line


def test_sessions_of_different_applications_are_not_compared(folder, capfd):
    bench = hil_here(capfd, "bench", "identify", "--duration", "1", "--out", "bench.mcap",
                     cwd=folder)
    assert bench.returncode == 0, bench.stderr
    done = hil_here(capfd, "compare", "base.mcap", "bench.mcap", cwd=folder)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.strip().splitlines() == [
        "hil: error: different applications: the baseline is a servo session, the candidate "
        "a bench-identify session"]


def test_a_truncated_baseline_is_compared_over_what_was_read(folder, capsys):
    """The series base_000, base_001 (cut in half: the writer killed), the rest lost."""
    assert (folder / "base_002.mcap").exists() and not (folder / "base.mcap").exists()
    (folder / "cut_000.mcap").write_bytes((folder / "base_000.mcap").read_bytes())
    blob = (folder / "base_001.mcap").read_bytes()
    (folder / "cut_001.mcap").write_bytes(blob[: len(blob) // 2])
    done = hil_here(capsys, "compare", "cut.mcap", "again.mcap", "--signal", POSITION,
                    "--json", cwd=folder)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    [row] = result["rows"]  # the KPIs are written at the end: the cut file has none
    assert row["name"] == POSITION and row["difference"] == 0
    notes = "\n".join(result["notes"])
    assert "baseline is a recovered file (cut_001.mcap: " in notes and "recorded none" in notes
    assert f"{POSITION}: compared over " in notes and "the candidate 1000" in notes
    changed = hil_here(capsys, "compare", "cut.mcap", "stiffer.mcap", "--signal", POSITION,
                       cwd=folder)
    assert changed.returncode == 1 and POSITION in changed.stderr
    nothing = hil_here(capsys, "compare", "cut.mcap", "again.mcap", cwd=folder)
    assert nothing.returncode == 2 and "nothing to compare" in nothing.stderr


@pytest.mark.realtime  # on the wall clock at 2 kHz: at nice 0, ahead of the niced rest
def test_real_time_is_interpolated_onto_the_baselines_ticks(tmp_path, capsys):
    # its own baseline, the module's base.mcap recorded in this process: the real-time tests
    # run apart, where the module's three sessions would be recorded again for this one
    folder = tmp_path
    (folder / "my_controllers.py").write_text(PD)
    base = hil_here(capsys, "servo", "run", "--controller", "my_controllers.py:Pd", "--param",
                    "kp=300", "--duration", "0.5", "--out", "base.mcap", "--quiet",
                    "--split-duration", "0.25", cwd=folder)
    assert base.returncode == 0, base.stderr
    run = hil_here(capsys, "servo", "run", "--controller", "my_controllers.py:Pd",
                   "--duration", "0.3", "--realtime", "--out", "wall.mcap", "--quiet", cwd=folder)
    assert run.returncode in (0, 3), run.stderr  # 3: the wall clock disturbed it (a busy CPU)
    refused = hil_here(capsys, "compare", "base.mcap", "wall.mcap", "--signal", POSITION,
                       cwd=folder)
    assert refused.returncode == 2 and "real-time sessions need a tolerance" in refused.stderr
    done = hil_here(capsys, "compare", "base.mcap", "wall.mcap", "--tolerance", "*=abs:1e9",
                    "--signal", POSITION, "--json", cwd=folder)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["alignment"] == "interpolated"
    assert result["notes"][0] == ("real-time sessions: the candidate interpolated onto the "
                                  "baseline's ticks")
    row = next(r for r in result["rows"] if r["name"] == POSITION)
    assert row["tolerance"] == "abs 1e+09 deg" and row["worst_t_s"] <= 0.3


def test_interpolation_and_the_tube_on_other_tick_grids():
    base_t = np.arange(0, 1_000_000_000, 500_000)                  # 2 kHz
    cand_t = np.arange(130_000, 1_000_000_000, 700_000)            # another grid, later start
    ramp = Series(base_t, base_t * 2e-9)
    aligned = interpolated(ramp, Series(cand_t, cand_t * 2e-9))
    assert aligned.t_s[0] >= 130e-6 and aligned.t_s[-1] <= cand_t[-1] / 1e9
    assert np.allclose(aligned.candidate, aligned.baseline, rtol=0, atol=1e-12)  # a line
    assert tick_for_tick(ramp, Series(cand_t, cand_t * 2e-9)).t_s.size == \
        np.intersect1d(base_t, cand_t).size
    sine = Series(base_t, np.sin(2 * np.pi * base_t / 1e9))
    late = Series(cand_t, np.sin(2 * np.pi * np.clip(cand_t - 1_000_000, 0, None) / 1e9))
    lagged = interpolated(sine, late)  # the same sine 1 ms later
    missed = judge_signal(parse_tolerance("abs:0.001"), lagged, sine)
    assert not missed.passed and missed.difference > 0.004
    assert judge_signal(parse_tolerance("tube:0.0005,1.5ms"), lagged, sine).passed
    assert not judge_signal(parse_tolerance("tube:0.0005,0.5ms"), lagged, sine).passed


USER_TEST = textwrap.dedent("""
    import os
    from my_controllers import Pd

    def test_pd(hil_drive, hil_baseline):
        hil_drive.run(Pd, {"kp": 300.0}, duration_s=0.3)
        hil_baseline.check(name="fixed")
        hil_drive.run(Pd, {"kp": float(os.environ["KP"])}, duration_s=0.3)
        hil_baseline.check(name="env")
""")


def test_the_pytest_baseline_records_then_fails_on_a_changed_controller(tmp_path):
    (tmp_path / "my_controllers.py").write_text(PD)
    (tmp_path / "test_mine.py").write_text(USER_TEST)

    def pytest_run(kp: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
             *NOT_A_USERS_PLUGINS, "-n", "0",
             "--basetemp", str(tmp_path / f"runs-{kp}"), "test_mine.py",
             *(["--hil-html", "pages"] if kp == "250" else [])],
            cwd=tmp_path, env={**ENV, "KP": kp}, capture_output=True, text=True,
            timeout=150, check=False)

    first = pytest_run("300")
    assert first.returncode == 0, first.stdout + first.stderr
    assert "1 passed" in first.stdout and first.stdout.count("BaselineRecorded: ") == 2
    files = sorted((tmp_path / "baselines").iterdir())
    assert [f.name for f in files] == ["test_pd-env.mcap", "test_pd-fixed.mcap"]
    assert all(f.stat().st_size < 60_000 for f in files)  # 0.3 s at 2 kHz, two signals
    second = pytest_run("250")
    assert second.returncode == 1, second.stdout + second.stderr
    assert "1 failed" in second.stdout and "BaselineRecorded" not in second.stdout
    # the fixture's runs start where the axis stands: positions from each run's start
    assert f"{POSITION} (from start) by " in second.stdout and " at t = " in second.stdout
    assert "outside tolerance" in second.stdout and "FAIL" in second.stdout
    runs = tmp_path / "runs-250"
    same = json.loads(next(runs.rglob("test_pd-fixed.compare.json")).read_text())
    assert same["passed"] and all(row["difference"] == 0 for row in same["rows"])
    changed = json.loads(next(runs.rglob("test_pd-env.compare.json")).read_text())
    assert changed["passed"] is False and changed["alignment"] == "lockstep"
    assert f"comparison: {next(runs.rglob('test_pd-env.compare.json'))}" in second.stdout
    failed_page = next(runs.rglob("test_pd-env.compare.html"))
    assert f"(report: {failed_page})" in second.stdout and "FAILED" in failed_page.read_text()
    pages = sorted(p.name for p in (tmp_path / "pages").iterdir())
    assert pages == ["test_pd-env.compare.html", "test_pd-fixed.compare.html",
                     "test_pd-servo-1.html", "test_pd-servo-2.html"]


def test_a_one_sided_tolerance_bounds_a_signal_on_its_side_only():
    """``max:`` lets a signal fall any amount below the baseline and rise at most V above it,
    ``min:`` the other way round; the worst tick is the one furthest out on the bounded side."""
    t = np.arange(0, 10_000_000, 1_000_000)
    base = Series(t, np.zeros(t.size))
    cand = Series(t, np.where(np.arange(t.size) == 3, 5.0, -5.0))  # far below, once above
    aligned = tick_for_tick(base, cand)
    assert not judge_signal(parse_tolerance("max:1"), aligned, base).passed
    assert judge_signal(parse_tolerance("max:1"), aligned, base).index == 3
    assert judge_signal(parse_tolerance("max:5"), aligned, base).passed
    lower = judge_signal(parse_tolerance("min:1"), aligned, base)
    assert not lower.passed and lower.difference == pytest.approx(4.0) and lower.index != 3
    assert not judge_signal(parse_tolerance("abs:4.5"), aligned, base).passed  # both ways
