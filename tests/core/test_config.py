import pytest

from hil.core.config import deep_merge, load_toml, lookup, parse_toml
from hil.core.errors import ConfigError


def test_toml_syntax_error_names_the_file_and_line(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[bench]\nport = \n")
    with pytest.raises(ConfigError, match=r"c\.toml: invalid TOML: .*line 2"):
        load_toml(path)


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_toml(tmp_path / "none.toml")


def test_lookup_checks_types_and_names_the_key():
    cfg = parse_toml("[a]\nport = 'x'\nflag = true\nrate = 100\n", "t")
    assert lookup(cfg, "a.rate", float) == 100.0
    with pytest.raises(ConfigError, match=r"'a\.port' must be int"):
        lookup(cfg, "a.port", int)
    with pytest.raises(ConfigError, match=r"'a\.flag' must be float or int"):
        lookup(cfg, "a.flag", float)  # TOML true is not a number
    with pytest.raises(ConfigError, match=r"missing key 'a\.nothing'"):
        lookup(cfg, "a.nothing", int)
    assert lookup(cfg, "a.nothing", int, default=7) == 7


def test_deep_merge_overrides_leaves_and_keeps_the_rest():
    base = {"bench": {"port": 5020, "relays": {"M1": 0, "M2": 1}}}
    merged = deep_merge(base, {"bench": {"relays": {"M2": 5}}})
    assert merged == {"bench": {"port": 5020, "relays": {"M1": 0, "M2": 5}}}
    assert base["bench"]["relays"]["M2"] == 1
