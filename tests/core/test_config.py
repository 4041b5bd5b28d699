import pytest

from hil.core.config import Table, deep_merge, load_toml, parse_toml
from hil.errors import ConfigError


def test_toml_syntax_error_names_the_file_and_line(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text("[bench]\nport = \n")
    with pytest.raises(ConfigError, match=r"c\.toml: invalid TOML: .*line 2"):
        load_toml(path)


def test_missing_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_toml(tmp_path / "none.toml")


def test_deep_merge_overrides_leaves_and_keeps_the_rest():
    base = {"bench": {"port": 5020, "relays": {"M1": 0, "M2": 1}}}
    merged = deep_merge(base, {"bench": {"relays": {"M2": 5}}})
    assert merged == {"bench": {"port": 5020, "relays": {"M1": 0, "M2": 5}}}
    assert base["bench"]["relays"]["M2"] == 1


def test_table_reads_typed_values_and_names_file_and_key():
    t = Table(parse_toml("[bus]\ntimeout_s = 1\nattempts = 2\nurl = 'x'\nfast = true\n",
                         "bench.toml"), "bench.toml")
    bus = t.table("bus")
    assert bus.number("timeout_s", above=0) == 1.0 and isinstance(bus.number("timeout_s"), float)
    assert bus.integer("attempts", at_least=1) == 2
    assert bus.string("url") == "x" and bus.boolean("fast") is True
    assert bus.number("missing_s", 0.5) == 0.5 and bus.integer("maybe", None) is None
    with pytest.raises(ConfigError, match=r"^bench\.toml: key 'bus\.url' must be a number, "
                                          r"got a string 'x'$"):
        bus.number("url")
    with pytest.raises(ConfigError,
                       match=r"key 'bus\.fast' must be an integer, got a boolean true"):
        bus.integer("fast")  # TOML true is not a number
    with pytest.raises(ConfigError, match=r"^bench\.toml: missing key 'bus\.nothing'$"):
        bus.integer("nothing")


def test_table_checks_ranges_and_choices():
    t = Table({"period_s": 0.0, "n": 300, "mode": "fast", "x": float("nan")}, "f.toml", "loop")
    with pytest.raises(ConfigError, match=r"key 'loop\.period_s' must be > 0 s, got 0 s"):
        t.number("period_s", above=0)
    with pytest.raises(ConfigError, match=r"key 'loop\.n' must be <= 255, got 300"):
        t.integer("n", at_most=255)
    with pytest.raises(ConfigError, match=r"key 'loop\.n' must be >= 500, got 300"):
        t.integer("n", at_least=500)
    with pytest.raises(ConfigError, match=r"key 'loop\.mode' must be one of cst, csp, got 'fast'"):
        t.string("mode", choices=("cst", "csp"))
    with pytest.raises(ConfigError, match=r"key 'loop\.x' must be a finite number"):
        t.number("x")


def test_table_done_refuses_keys_nobody_read():
    t = Table(parse_toml("[relays.P1]\ncoil = 2\ndwel_s = 5.0\n", "my.toml"), "my.toml")
    relays = t.table("relays")
    assert relays.names() == ["P1"]
    p1 = relays.table("P1")
    p1.integer("coil")
    p1.number("dwell_s", 5.0)
    with pytest.raises(ConfigError, match=r"^my\.toml: unknown key 'relays\.P1\.dwel_s' "
                                          r"\(did you mean 'relays\.P1\.dwell_s'\? known "
                                          r"here: coil, dwell_s\)$"):
        p1.done()
    relays.done()  # P1 itself was read
    t.done()


def test_table_refuses_a_value_where_a_table_belongs():
    with pytest.raises(ConfigError, match=r"key 'bus' must be a table, got an integer 3"):
        Table({"bus": 3}, "c.toml").table("bus")
    with pytest.raises(ConfigError, match=r"missing key 'bus'"):
        Table({}, "c.toml").table("bus", required=True)
    assert Table({}, "c.toml").table("bus").names() == []


def test_a_params_file_with_a_key_of_several_lines_is_one_error_line(tmp_path):
    # found by the fuzz campaign (benchmarks/fuzz.py): the key "\n" of a --params file put
    # its line break into the error
    from hil.core.params import read_params_file

    path = tmp_path / "best.toml"
    path.write_text('"\\n" = []\n')
    with pytest.raises(ConfigError) as refused:
        read_params_file(str(path))
    assert str(refused.value) == (f"{path}: '\\n': a parameter is a number, true/false or "
                                  "text (an axis' own in its [AXIS] table), got []")


def test_an_unknown_key_of_several_lines_is_named_on_one(tmp_path):
    # found by the fuzz campaign (benchmarks/fuzz.py): the key "\n" put its line break into
    # the unknown key's error
    table = Table(parse_toml('"\\n" = 1\n', "c.toml"), "c.toml")
    with pytest.raises(ConfigError) as refused:
        table.done()
    assert str(refused.value) == "c.toml: unknown key '\\n' (known here: none)"
