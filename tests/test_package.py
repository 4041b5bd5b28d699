"""The installed package: a wheel built from this checkout puts one top-level name, ``hil``, on
the user's path; the checkout's drivers/, controllers/ and emulators/ are inside it."""

from __future__ import annotations

import json
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import hil

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow

# what the fresh venv runs: its own top-level names, and the three folders under hil
PROBE = """
import importlib.metadata as md, json
import hil.controllers.errors, hil.drivers.errors, hil.emulators.errors, hil.protocols.cia301
tops = sorted({f.parts[0] for f in md.distribution("hil").files
               if not f.parts[0].endswith(".dist-info") and f.parts[0] != ".."})
missing = []
for name in ("drivers", "controllers", "emulators"):
    try:
        __import__(name)
    except ModuleNotFoundError:
        missing.append(name)
print(json.dumps({"tops": tops, "missing": missing, "file": hil.drivers.errors.__file__}))
"""


def test_the_wheel_installs_hil_alone(tmp_path):
    subprocess.run([sys.executable, "-m", "hatchling", "build", "-t", "wheel", "-d",
                    str(tmp_path / "dist")], cwd=ROOT, check=True, capture_output=True)
    wheel = next((tmp_path / "dist").glob("hil-*.whl"))
    names = zipfile.ZipFile(wheel).namelist()
    assert {name.split("/")[0] for name in names} == {"hil", f"hil-{hil.__version__}.dist-info"}
    assert "hil/drivers/canopen/master.py" in names and "hil/protocols/cia402.py" in names
    assert "hil/configs/drive.toml" in names            # the packaged configuration comes along

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    python = venv / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet",
                    "--no-deps", "--no-index", str(wheel)], check=True, capture_output=True)
    probe = subprocess.run([str(python), "-I", "-c", PROBE], cwd=tmp_path, check=True,
                           capture_output=True, text=True)
    seen = json.loads(probe.stdout)
    assert seen["tops"] == ["hil"]
    assert seen["missing"] == ["drivers", "controllers", "emulators"]
    assert seen["file"].startswith(str(venv))           # the installed copy, not the checkout
