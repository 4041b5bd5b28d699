"""Files into hil: the bench and drive configs (TOML), ``--params`` and tolerances files,
model files and EDS files, each a valid file of hil's (or a real drive's) with one or a few
values changed, a key or line removed or added, or its text cut; written to a real file and
read by the function the command line reads it with, then used as a run would use it (the
bench emulator built, the emulated drive started and cycled, the twin of an EDS answering
its master).

The rule: a clear error of one line naming the problem (a ConfigError, an
EmulatorSetupError, a DriveError), or a file that works, never another exception, a hang or
an emulator's internal error.
"""

from __future__ import annotations

import contextlib
import os
import re
import struct
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import tomli_w
from hypothesis import strategies as st

from hil.bench.config import load_bench_config
from hil.bench.emulated import make_emulator
from hil.compare.tolerances import tolerances_file
from hil.controllers.servo.model import published_axis_model
from hil.core.config import parse_toml
from hil.core.params import read_params_file
from hil.drivers.canopen.eds import check, import_description
from hil.emulators.drive.axis_model import axis_model_file
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.runners import LockstepDrive
from hil.protocols.cia402 import OPERATION_MODES
from hil.servo.config import load_drive_config
from hil.servo.rig import EmulatedDrive
from tests.fuzz.harness import Check, Target, bound, clear_error

CONFIGS = Path(__file__).resolve().parents[2] / "hil" / "configs"
EDS_FILE = Path(__file__).resolve().parents[1] / "data" / "ex20_gear.eds"

# -- values of any TOML type, and the edits of a table -------------------------------------
SCALARS = st.one_of(st.integers(-2**63, 2**63 - 1), st.sampled_from([0, -1, 1, 2**31, 2**32]),
                    st.floats(allow_nan=True), st.sampled_from([0.0, -0.0, 1e-12, 1e300]),
                    st.booleans(), st.text(max_size=12),
                    st.sampled_from(["", "x", "modbus-tcp://127.0.0.1:1", "socketcand://:0",
                                     "cst", "csp", "1e3", "drop@1", "rel:2%"]))
VALUES = st.one_of(SCALARS, st.lists(SCALARS, max_size=3),
                   st.dictionaries(st.text(min_size=1, max_size=6), SCALARS, max_size=2))


def key_paths(table: dict[str, Any], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every key of ``table`` and its sub-tables, as a path."""
    paths = []
    for key, value in table.items():
        paths.append((*prefix, key))
        if isinstance(value, dict):
            paths += key_paths(value, (*prefix, key))
    return paths


@st.composite
def edited(draw: st.DrawFn, table: dict[str, Any]) -> dict[str, Any]:
    """``table`` with 1-3 edits: a value replaced (by one of any type), a key removed, or an
    unknown key added, anywhere."""
    import copy

    out = copy.deepcopy(table)
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(key_paths(out) or [("x",)]))
        parent = out
        for key in path[:-1]:
            parent = parent[key]
        how = draw(st.sampled_from(["replace", "replace", "replace", "remove", "add"]))
        if how == "replace":
            parent[path[-1]] = draw(VALUES)
        elif how == "remove":
            parent.pop(path[-1], None)
        else:
            parent[draw(st.text(min_size=1, max_size=8))] = draw(VALUES)
    return out


def toml_text(table: dict[str, Any]) -> str:
    """``table`` as TOML (a float nan/inf written as TOML's own)."""
    try:
        return tomli_w.dumps(table)
    except (TypeError, ValueError):
        return ""


@st.composite
def texts(draw: st.DrawFn, text: str) -> str:
    """``text`` with a line removed, cut, or a line of junk inserted."""
    lines = text.splitlines(keepends=True)
    at = draw(st.integers(0, max(0, len(lines) - 1)))
    how = draw(st.sampled_from(["drop", "cut", "junk"]))
    if how == "drop":
        del lines[at:at + 1]
    elif how == "cut":
        return text[:draw(st.integers(0, len(text)))]
    else:
        lines.insert(at, draw(st.text(max_size=30)) + "\n")
    return "".join(lines)


def config_cases(name: str) -> st.SearchStrategy[str]:
    text = (CONFIGS / name).read_text()
    table = parse_toml(text, name)
    return st.one_of(edited(table).map(toml_text), edited(table).map(toml_text), texts(text))


@contextlib.contextmanager
def _file(suffix: str) -> Iterator[Callable[[str], str]]:
    """A writer of the case's text to one real file (the same path each time)."""
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, f"case{suffix}")

        def write(text: str) -> str:
            with open(path, "w", encoding="utf-8", errors="surrogateescape") as file:
                file.write(text)
            return path

        yield write


@contextlib.contextmanager
def bench_config_rig() -> Iterator[Check]:
    with _file(".toml") as write:
        def check(text: str) -> None:
            path = write(text)
            with bound("a bench config"):
                try:
                    config = load_bench_config(path)
                    make_emulator(config)
                except Exception as exc:
                    clear_error(exc)

        yield check


@contextlib.contextmanager
def drive_config_rig() -> Iterator[Check]:
    """The config read, then its emulated drive started and cycled as a run would."""
    with _file(".toml") as write:
        def check(text: str) -> None:
            path = write(text)
            with bound("a drive config"):
                try:
                    config = load_drive_config(path)
                    master = EmulatedDrive(config.master, config.emulator)
                except Exception as exc:
                    clear_error(exc)
                    return
                try:
                    master.start()
                    for _ in range(5):
                        master.exchange(10.0)
                except Exception as exc:
                    clear_error(exc)
                finally:
                    master.close()
                assert master.emulator.node.internal_errors == 0

        yield check


@contextlib.contextmanager
def small_files_rig() -> Iterator[Check]:
    """A ``--params`` file and a tolerances file (any TOML table)."""
    with _file(".toml") as write:
        def check(text: str) -> None:
            path = write(text)
            for read in (read_params_file, tolerances_file):
                try:
                    read(path)
                except Exception as exc:
                    clear_error(exc)

        yield check


SMALL_TABLES = st.dictionaries(st.text(min_size=1, max_size=8) | st.sampled_from(
    ["*", "kp", "rms_error_deg", "/drive/feedback:position_deg"]), st.one_of(
        VALUES, st.sampled_from(["exact", "abs:0.1", "rel:2%", "tube:0.01,2ms", "tube:1,",
                                 "abs:-1", "rel:nan%", "tube:1,1e999ms", "abs:inf"])),
    max_size=4).map(toml_text)


# -- model files ------------------------------------------------------------------------------
MODEL = axis_model_file(published_axis_model())
NUMBER = re.compile(r"-?\d+(\.\d+)?([eE][-+]?\d+)?")


@st.composite
def model_texts(draw: st.DrawFn) -> str:
    """The published axis' model file with numbers changed, a line removed or junk added."""
    text = MODEL
    if draw(st.booleans()):
        numbers = list(NUMBER.finditer(text))
        for _ in range(draw(st.integers(1, 4))):
            match = draw(st.sampled_from(numbers))
            new = draw(st.sampled_from(["0", "-1", "1e308", "-1e308", "1e-320", "NaN",
                                        "Infinity", "2", "1e9", '"x"', "[]", "null"]) |
                       st.floats(allow_nan=False).map(repr))
            text = text[:match.start()] + new + text[match.end():]
            numbers = list(NUMBER.finditer(text))
        return text
    return draw(texts(text))


@contextlib.contextmanager
def model_rig() -> Iterator[Check]:
    """The model file named by a drive config's ``[emulator] model`` (as ``hil emulate drive
    --model`` and ``emulated?model=`` name it), read with the config, then the emulated drive
    run on it: started, 40 cycles of 500 mA."""
    with tempfile.TemporaryDirectory() as folder:
        model, config = os.path.join(folder, "model.json"), os.path.join(folder, "drive.toml")
        with open(config, "w", encoding="utf-8") as file:
            file.write('[emulator]\nmodel = "model.json"\n')

        def check(text: str) -> None:
            with open(model, "w", encoding="utf-8", errors="surrogateescape") as file:
                file.write(text)
            with bound("a model file"):
                try:
                    drive = load_drive_config(config)
                except Exception as exc:
                    clear_error(exc)
                    return
                master = EmulatedDrive(drive.master, drive.emulator)
                try:
                    master.start()
                    for _ in range(40):
                        master.exchange(500.0)
                except Exception as exc:
                    clear_error(exc)
                finally:
                    master.close()
                assert master.emulator.node.internal_errors == 0, "the drive failed on its model"

        yield check


# -- EDS files --------------------------------------------------------------------------------
EDS = EDS_FILE.read_text(encoding="latin-1")
EDS_KEYS = ("DataType", "AccessType", "DefaultValue", "PDOMapping", "SubNumber", "ObjectType",
            "LowLimit", "HighLimit", "ParameterValue", "CompactSubObj", "VendorNumber",
            "ProductNumber", "SupportedObjects")
EDS_VALUES = st.sampled_from(["", "0", "0x", "-1", "0x7", "0x9", "0xFFFFFFFFFF", "$NODEID",
                              "$NODEID+0x180", "$NODEID+x", "abc", "1e3", "rw", "ro", "wo",
                              "const", "rww", "rwr", "0x0007", "0x0A", "0x20", "8", "255",
                              "0x80000181", "2147483648"]) | st.text(max_size=8)


@st.composite
def eds_texts(draw: st.DrawFn) -> str:
    """A real drive's EDS with values changed (the keys that describe objects, mostly), a
    line removed, or its text cut."""
    lines = EDS.splitlines(keepends=True)
    keyed = [i for i, line in enumerate(lines) if line.split("=")[0] in EDS_KEYS]
    for _ in range(draw(st.integers(1, 3))):
        how = draw(st.sampled_from(["value", "value", "value", "drop", "section"]))
        at = draw(st.sampled_from(keyed))
        key = lines[at].split("=")[0]
        if how == "value":
            lines[at] = f"{key}={draw(EDS_VALUES)}\n"
        elif how == "drop":
            lines[at] = "\n"
        else:  # a section's name changed: another object, or none that parses
            sections = [i for i, line in enumerate(lines) if line.startswith("[")]
            lines[draw(st.sampled_from(sections))] = f"[{draw(EDS_VALUES)}]\n"
    return "".join(lines)


@contextlib.contextmanager
def eds_rig() -> Iterator[Check]:
    """The EDS read as ``hil drive scan --eds`` and the master's ``[master] eds`` read it,
    then as the twin's (``hil emulate drive --eds``), whose node answers an SDO read of every
    object it has."""
    with _file(".eds") as write:
        def check(text: str) -> None:
            path = write(text)
            with bound("an EDS"):
                try:
                    check_od(import_description(path, 1))
                except Exception as exc:
                    clear_error(exc)
                try:
                    drive = LockstepDrive(DriveEmulatorConfig(eds=path))
                except Exception as exc:
                    clear_error(exc)
                    return
                bus = drive.attach_bus()
                try:
                    for var in drive.node.objects.od.values():
                        for sub in getattr(var, "subindices", {0: None}):
                            bus.send_frames([(0x601, struct.pack("<BHBI", 0x40, var.index,
                                                                 sub, 0))])
                            drive.pump()
                    assert drive.node.internal_errors == 0, "the twin failed on its EDS"
                finally:
                    bus.shutdown()
                    drive.close()

        yield check


def check_od(od: Any) -> None:
    for mode in OPERATION_MODES.values():
        assert all(isinstance(line, str) for line in check(od, mode))


DRIVE_TOML = (CONFIGS / "drive.toml").read_text()
BENCH_TOML = (CONFIGS / "bench.toml").read_text()
TARGETS = (
    Target("toml-bench-config", config_cases("bench.toml"), bench_config_rig, examples=60,
           # found: a negative plant seed taken, then numpy's ValueError building the plant
           regressions=(re.sub(r"\nseed = \d+", "\nseed = -1", BENCH_TOML),)),
    Target("toml-drive-config", config_cases("drive.toml"), drive_config_rig, examples=40,
           # found: a 33-bit cycle period taken, then struct.error packing 0x1006
           regressions=(re.sub(r"cycle_period_us = \d+", "cycle_period_us = 4294967296",
                               DRIVE_TOML),
                        # found: a friction that pushes ran the axis to inf (internal errors)
                        re.sub(r"viscous_mA_per_deg_s = [-\d.]+", "viscous_mA_per_deg_s = -747",
                               DRIVE_TOML),
                        re.sub(r"viscous_mA_per_deg_s = [-\d.]+", "viscous_mA_per_deg_s = 1498",
                               DRIVE_TOML))),
    Target("toml-params-tolerances", SMALL_TABLES, small_files_rig, examples=150,
           regressions=('"\\n" = []\n',)),  # found: its line break in the one-line error
    Target("model-file", model_texts(), model_rig, examples=40,
           # found: a model that runs away took the drive's position to inf (internal errors)
           regressions=(MODEL.replace("[0.18, 0.82,", "[-2.4747881765574195e+17, 0.82,"),
                        MODEL.replace('"y_offset": [0.0]', '"y_offset": [1e308]'),
                        MODEL.replace('"u_offset": [0.0]', '"u_offset": [1e308]'),
                        MODEL.replace('"order": 4', '"order": Infinity'))),
    Target("eds-file", eds_texts(), eds_rig, examples=30,
           # found: a string beyond ASCII took the twin's SDO read to an internal error
           regressions=(re.sub(r"(\[1009\][^\[]*DefaultValue=)[^\n]*",
                               lambda m: m.group(1) + "z3\u00a4", EDS),)),
)
