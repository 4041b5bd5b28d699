"""The twins guide's "Make a twin of your machine" (docs/guides/twins.md), its commands run
as a user runs them: from a copy of examples/twin/ outside the repository, each `hil` line of
the page's first sh block in turn, by ``main`` in this process (:func:`hil_here`: each command
runs as a ``hil`` process from outside the repository in its own tests, tests/servo/
test_identify_axis.py and test_twin_check.py among them). "The machine" (machine.toml: another axis,
viscous friction) is identified, its twin checked against a PID run of it, and the
controllers' KPIs on the twin come within a hair of the machine's; a machine with Coulomb
friction, which a linear twin cannot hold, fails its check."""

from __future__ import annotations

import json
import math
import re
import runpy
import shlex
import shutil
from pathlib import Path

import pytest

from hil.cli.identify import SERVO_UNITS, analyse_model, analysis_json
from hil.controllers.ident.model_file import loads_model
from hil.core.recording.reader import read_session
from tests.cli import hil_here
from tests.docs import blocks, page

pytestmark = [pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "examples" / "twin"


def readme_commands() -> list[list[str]]:
    """The `hil` lines of the first sh block of the twins guide."""
    first = blocks(page("guides/twins.md"), "sh")[0]
    lines = [line.split("  #")[0].strip() for line in first.splitlines()]
    return [shlex.split(line)[1:] for line in lines if line.startswith("hil ")]


@pytest.fixture
def machine(tmp_path: Path) -> Path:
    folder = tmp_path / "machine"
    shutil.copytree(EXAMPLE, folder, ignore=shutil.ignore_patterns("__pycache__"))
    return folder


def test_the_guide_makes_a_twin_that_fits_the_machine_and_predicts_its_kpis(machine, capfd):
    commands = readme_commands()
    assert [c[:2] for c in commands[:4]] == [["servo", "identify"], ["identify",
                                              "identify.mcap"], ["servo", "run"],
                                             ["twin", "check"]]
    kpis, printed = {}, {}
    for args in commands:
        done = hil_here(capfd, *args, cwd=machine)
        assert done.returncode == 0, (args, done.stdout[-2000:], done.stderr[-2000:])
        printed[args[0]] = done.stdout
        if "--json" in args and args[:2] == ["servo", "run"]:
            kpis[args[args.index("--out") + 1].removesuffix(".mcap")] = json.loads(done.stdout)

    model_text = (machine / "twin.json").read_text()
    assert json.loads(model_text)["fit_pct"] > 99.0
    # the analysis `hil identify --json` prints, of the twin the guide wrote (the same
    # function on the same model: identifying it a second time cost 3-9 s)
    analysis = analysis_json(analyse_model(loads_model(model_text)), SERVO_UNITS)
    resonance = max(analysis["resonances"], key=lambda r: r["peak_gain"])
    assert resonance["frequency_hz"] == pytest.approx(560.0, abs=2.0)  # the machine's
    assert resonance["damping_ratio"] == pytest.approx(0.02, rel=0.1)
    assert analysis["integrators"] == 1  # viscous friction: the speed settles, 1 deg/s per mA
    assert analysis["integrator_gain"][0][0] == pytest.approx(1.0, rel=0.02)

    # the guide's twin check's report (its --json form: tests/servo/test_twin_check.py)
    fits = re.findall(r"^  (\w+) +fit +([\d.]+) %", printed["twin"], re.M)
    assert [name for name, _ in fits] == ["position_deg", "velocity_deg_s"], printed["twin"]
    assert all(float(fit) > 99.0 for _, fit in fits)
    # and the guide says the figures the commands print (hil/core/kpi_text.py's fit_text)
    said = re.search(r"\| fit \| \| ([\d.]+) % held out; twin check of the PID run: ([\d.]+) % "
                     r"position, ([\d.]+) % velocity \|", page("guides/twins.md"))
    assert said, "the guide's fit row"
    held_out = re.search(r"^fit_pct: +([\d.]+) %", printed["identify"], re.M)
    assert held_out and said.groups() == (held_out.group(1), *(fit for _, fit in fits)), \
        (said.groups(), printed["identify"][:600], fits)
    assert (machine / "twin-check.png").stat().st_size > 0
    for controller in ("pid", "mpc"):
        on_machine, on_twin = kpis[f"machine-{controller}"], kpis[f"twin-{controller}"]
        for key in ("max_error_deg", "rms_error_deg"):
            assert on_twin[key] == pytest.approx(on_machine[key], rel=0.02), (controller, key)
    twin_run = read_session(str(machine / "twin-pid.mcap"))
    tables = json.loads(twin_run.metadata["config"]["json"])["drive"]["emulator"]
    assert tables["model"].endswith("twin.json") and tables["friction"]["viscous_mA_per_deg_s"] == 0


def test_a_machine_with_coulomb_friction_fails_the_check_of_a_linear_twin(machine, capfd):
    """The guide's first four commands on another machine: a variant of the guide's run."""
    (machine / "machine.toml").write_text((machine / "machine.toml").read_text()
                                          + "coulomb_mA = 20.0\ncoulomb_smoothing_deg_s = 2.0\n")
    for args in readme_commands()[:4]:
        done = hil_here(capfd, *args, cwd=machine)
    assert done.returncode == 1, done.stdout + done.stderr  # the twin check, last of the four
    assert "FAIL: every output's fit must reach 80 %" in done.stdout


def test_the_machine_model_is_what_make_machine_writes(tmp_path, monkeypatch):
    """``python make_machine.py`` in its folder, run in this process as ``python`` runs it (a
    process start, scipy's import included, costs about a second; what the script writes is
    what this checks)."""
    shutil.copy(EXAMPLE / "make_machine.py", tmp_path)
    monkeypatch.chdir(tmp_path)
    runpy.run_path(str(tmp_path / "make_machine.py"), run_name="__main__")
    written = json.loads((tmp_path / "machine_axis.json").read_text())
    committed = json.loads((EXAMPLE / "machine_axis.json").read_text())
    # the same file but for the last digits of its floats, which depend on the CPU (scipy's
    # matrix exponential differs in the 16th digit from one machine to the next)
    assert written == _floats_within(committed, written)


def _floats_within(expected: object, actual: object, rel: float = 1e-12) -> object:
    """``expected`` with each float replaced by ``actual``'s where the two agree to ``rel``."""
    if isinstance(expected, float) and isinstance(actual, float):
        return actual if math.isclose(expected, actual, rel_tol=rel, abs_tol=1e-15) \
            else expected
    if isinstance(expected, list) and isinstance(actual, list) and len(expected) == len(actual):
        return [_floats_within(e, a, rel) for e, a in zip(expected, actual, strict=True)]
    if isinstance(expected, dict) and isinstance(actual, dict):
        return {k: _floats_within(v, actual.get(k), rel) for k, v in expected.items()}
    return expected
