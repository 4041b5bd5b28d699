"""URL scheme registry: lazy built-ins, a fallback, errors that list the known schemes."""

import sys

import pytest

from hil.core.registry import SchemeRegistry, scheme_of
from hil.errors import ConfigError


def test_scheme_of_urls_and_plain_words():
    assert scheme_of("modbus-tcp://127.0.0.1:5020") == "modbus-tcp"
    assert scheme_of("modbus-rtu:///dev/ttyUSB0") == "modbus-rtu"
    assert scheme_of("emulated") == "emulated"


def test_builtin_factories_are_imported_only_when_their_scheme_is_opened(tmp_path, monkeypatch):
    (tmp_path / "lazy_device_module.py").write_text(
        "def open_thing(url, *args, **kwargs):\n    return ('opened', url, args, kwargs)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = SchemeRegistry("widget", {"thing": ("lazy_device_module", "open_thing")})
    assert "lazy_device_module" not in sys.modules
    assert registry.schemes() == ["thing"]
    assert registry.open("thing://a:1", 5, k=2) == ("opened", "thing://a:1", (5,), {"k": 2})
    assert "lazy_device_module" in sys.modules
    monkeypatch.delitem(sys.modules, "lazy_device_module")


def test_fallback_takes_the_schemes_the_table_does_not_name():
    def fallback(scheme):
        return (lambda url: f"bus {scheme} at {url}") if scheme in ("pcan", "kvaser") else None

    registry = SchemeRegistry("drive", {}, fallback=fallback)
    assert registry.open("pcan://PCAN_USBBUS1") == "bus pcan at pcan://PCAN_USBBUS1"
    with pytest.raises(ConfigError, match=r"^drive 'ftp://x': unknown scheme 'ftp'"):
        registry.factory("ftp://x")


def test_unknown_scheme_names_the_url_and_the_known_schemes():
    registry = SchemeRegistry("bench", {"modbus-tcp": ("m", "f"), "emulated": ("m", "g")})
    with pytest.raises(ConfigError, match=r"^bench 'modbus-udp://h:1': unknown scheme "
                                          r"'modbus-udp' \(known: emulated, modbus-tcp\)$"):
        registry.open("modbus-udp://h:1")


def test_installed_packages_add_schemes_through_the_entry_point_group(tmp_path, monkeypatch):
    """A distribution on sys.path (a dist-info folder, as pip leaves it) registers a scheme."""
    (tmp_path / "plugin_bench.py").write_text("def open_bench(url):\n    return 'plugin ' + url\n")
    info = tmp_path / "plugin_bench-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: plugin-bench\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[hil.test_devices]\nmy-bus = plugin_bench:open_bench\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = SchemeRegistry("bench", {"emulated": ("m", "g")}, "hil.test_devices")
    assert registry.schemes() == ["emulated", "my-bus"]
    assert registry.open("my-bus://x") == "plugin my-bus://x"
