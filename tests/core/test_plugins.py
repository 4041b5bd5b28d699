"""Loading a user's object from NAME, FILE.py:Class or package.module:Class."""

import importlib.metadata
import os
import sys

import pytest

from hil.core.params import merge_params, parse_param, parse_value
from hil.core.plugins import load_object
from hil.errors import ConfigError

GROUP = "hil.test_plugins"


def write_controller(path, body="class Threshold:\n    def __init__(self, params):\n"
                                "        self.params = params\n"):
    path.write_text(body)
    return path


def test_file_spec_relative_to_the_working_directory_and_absolute(tmp_path, monkeypatch):
    write_controller(tmp_path / "mine.py")
    monkeypatch.chdir(tmp_path)
    relative = load_object("mine.py:Threshold", GROUP)
    absolute = load_object(f"{tmp_path / 'mine.py'}:Threshold", GROUP)
    assert relative.__name__ == "Threshold" and relative is absolute  # loaded once
    assert relative({"on": 1}).params == {"on": 1}


def test_module_spec(tmp_path, monkeypatch):
    package = tmp_path / "labctl"
    package.mkdir()
    (package / "__init__.py").write_text("")
    write_controller(package / "ctl.py")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert load_object("labctl.ctl:Threshold", GROUP).__name__ == "Threshold"


def install(folder, name, entry):
    """A package ``name`` with ``entry`` in GROUP, as pip leaves it in ``folder`` (its
    bytecode, once imported, in a folder of its own: ``folder``'s time stays)."""
    (folder / name).mkdir()
    write_controller(folder / name / "__init__.py")
    info = folder / f"{name}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[{GROUP}]\n{entry} = {name}:Threshold\n")


def test_entry_point_name(tmp_path, monkeypatch):
    install(tmp_path, "plugin_ctl", "threshold")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert load_object("threshold", GROUP).__name__ == "Threshold"
    with pytest.raises(ConfigError, match=r"'thresold': no such name \(registered: threshold\)"):
        load_object("thresold", GROUP)


def test_entry_points_are_read_once_until_a_package_comes_or_goes(tmp_path, monkeypatch):
    reads = []
    read = importlib.metadata.entry_points

    def counted(**selection):
        reads.append(selection["group"])
        return read(**selection)

    monkeypatch.setattr(importlib.metadata, "entry_points", counted)
    site = tmp_path / "site"
    site.mkdir()
    install(site, "plugin_one", "one")
    # the path is this folder alone: no other folder's time (another test's, mypy's cache
    # made beside the suite) moves under the test
    monkeypatch.setattr(sys, "path", [str(site)])
    assert load_object("one", GROUP).__name__ == "Threshold"
    assert load_object("one", GROUP).__name__ == "Threshold"
    assert reads == [GROUP]  # the second run read no package's metadata
    # installed into a folder already on the path, a moment later: the folder's time moves
    install(site, "plugin_two", "two")
    later = site.stat().st_mtime_ns + 1_000_000_000
    os.utime(site, ns=(later, later))
    assert load_object("two", GROUP).__name__ == "Threshold"
    assert len(reads) == 2
    # a folder put on the path is a new state too
    other = tmp_path / "other"
    other.mkdir()
    install(other, "plugin_three", "three")
    sys.path.insert(0, str(other))
    assert load_object("three", GROUP).__name__ == "Threshold"
    assert len(reads) == 3


@pytest.mark.parametrize(("spec", "message"), [
    ("nowhere.py:Threshold", r"'nowhere.py:Threshold': no such file 'nowhere.py'"),
    ("mine.py:Missing", r"'mine.py:Missing': mine.py has no 'Missing' \(classes there: "
                        r"Threshold\)"),
    ("no_such_pkg.mod:X", r"'no_such_pkg.mod:X': no module named 'no_such_pkg.mod'"),
    ("broken.py:X", r"'broken.py:X': importing it failed: ZeroDivisionError: division by "
                    r"zero \(broken.py:2 in <module>\)"),
    ("mine.py:", r"expected NAME, FILE.py:Class or package.module:Class"),
    ("", r"an empty spec"),
])
def test_bad_specs_name_the_spec_and_the_reason(tmp_path, monkeypatch, spec, message):
    write_controller(tmp_path / "mine.py")
    (tmp_path / "broken.py").write_text("import math\nx = 1 / 0\n")
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ConfigError, match=message):
        load_object(spec, GROUP)


def test_params_parse_numbers_as_numbers():
    assert parse_value("3") == 3 and isinstance(parse_value("3"), int)
    assert parse_value("2.5") == 2.5 and parse_value("1e-3") == 0.001
    assert parse_value("true") is True and parse_value("False") is False
    assert parse_value("fast") == "fast" and parse_value("nan") == "nan"
    assert parse_param("gain = 2") == ("gain", 2)
    assert parse_param("y.gain=3") == ("y.gain", 3)  # axis y's, with --axes
    assert merge_params({"gain": 1, "mode": "a"}, ["gain=2", "limit=0.5"]) == \
        {"gain": 2, "mode": "a", "limit": 0.5}
    for bad in ("gain", "=3", "2x=1", "a.b.c=1", "y.=1", ".g=1"):
        with pytest.raises(Exception, match=r"expected KEY=VALUE"):
            parse_param(bad)
