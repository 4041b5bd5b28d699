"""What you configure is what runs, key by key and flag by flag, for both applications.

For every key the packaged configs document (every key their readers read), the test writes a
``--config`` file that sets it to another valid value and asks ``--print-config --json`` (the
settings the run itself is built from): the value must be the file's and its origin the file.
Then, for every key a flag sets, the flag overrides the file and must win. For every flag of
``hil servo run`` and ``hil bench run`` that sets no key, the flag must reach the run's options.
A key or a flag this test does not know fails it: a new one must say how it takes effect.
"""

from __future__ import annotations

import json
import re
import types
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.bench.run import BenchRunOptions
from hil.bench.settings import resolve_bench
from hil.cli.main import build_parser, main
from hil.controllers.ident.model_file import model_file_of
from hil.core.settings import Setting
from hil.servo.run import ServoRunOptions
from hil.servo.settings import resolve_servo

DATA = Path(__file__).parents[1] / "data"
AXIS_MODEL, OTHER_AXIS_MODEL = DATA / "axis-published.json", DATA / "axis-half-gain.json"
SERVO = resolve_servo(ServoRunOptions(controller="")).settings()
BENCH = resolve_bench(BenchRunOptions(controller="")).settings()


def toml_value(value: Any) -> str:
    """``value`` as TOML."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{json.dumps(k)} = {toml_value(v)}"
                                for k, v in value.items()) + " }"
    return repr(value)


def toml(keys: dict[str, Any]) -> str:
    """Dotted keys as a TOML document (each in the table of its head)."""
    tables: dict[str, list[str]] = {}
    for key, value in keys.items():
        head, _, name = key.rpartition(".")
        tables.setdefault(head, []).append(f"{name} = {toml_value(value)}")
    parts = [("" if not head else f"[{head}]\n") + "\n".join(lines) + "\n"
             for head, lines in sorted(tables.items(), key=lambda item: item[0] != "")]
    return "\n".join(parts)


def _fits(rule: str, value: float) -> bool:
    for op, bound in re.findall(r"(>=|<=|>|<)\s*(-?[0-9.e+]+)", rule):
        limit = float(bound)
        if not {">": value > limit, ">=": value >= limit, "<=": value <= limit,
                "<": value < limit}[op]:
            return False
    return True


def another(setting: Setting) -> Any:
    """A valid value of ``setting`` other than its own, from its kind and rule."""
    value, rule = setting.value, setting.rule
    if setting.kind == "boolean":
        return not value
    if rule.startswith("one of "):
        choices = [c.strip() for c in rule.removeprefix("one of ").split(",")]
        picked = next(c for c in choices if c != str(value))
        return int(picked) if setting.kind == "integer" else picked
    if setting.kind == "number":
        candidates = [value * 2, value * 0.5, value + 1, value - 1, 0.5] if value else [1.0, 0.5]
        return next(c for c in candidates if c != value and _fits(rule, c))
    if setting.kind == "integer":
        return next(c for c in (value + 1, value * 2, value - 1, 2)
                    if c != value and _fits(rule, c))
    return None


#: keys whose other value needs more than their kind (a string, an array, a relation to other
#: keys): pattern -> the keys to write (the first one is the key under test and its expected
#: value, unless "expect" says otherwise)
SPECIAL: dict[str, dict[str, Any]] = {
    # drive.toml
    "bus.interface": {"bus.interface": "virtual", "bus.channel": "bench-7"},
    "bus.channel": {"bus.interface": "virtual", "bus.channel": "bench-7"},
    "master.sync_echo": {"master.sync_echo": "0x2004:0"},
    # the keys that stand in for objects a drive lacks, and the homing method: none by default
    "master.increments_per_rev": {"master.increments_per_rev": 4096},
    "master.max_torque_permille": {"master.max_torque_permille": 800},
    "homing.method": {"homing.method": 17},
    # the emulated drive steps 500 us: its cycle is a multiple of it
    "master.cycle_period_us": {"master.cycle_period_us": 1000},
    "emulator.channel": {"emulator.channel": "can1"},
    "emulator.disturbance.end_s": {"emulator.disturbance.end_s": 1.5},
    "emulator.model": {"emulator.model": str(AXIS_MODEL)},  # a model file that fits the axis
    "emulator.faults": {"emulator.faults": ["drop_tpdo@1-2:every=3"]},
    "emulator.set": {"emulator.set": {"0x6075:0": 2000}},  # an object's power-on value
    # every key an [[axis]] takes: its own EDS and safety limits too
    "axis": {"axis": [{"name": "x", "node": 1, "current_limit_mA": 800.0, "eds": "x.eds",
                       "bus": "socketcand://127.0.0.1:29536",
                       "safety": {"following_error_deg": 5.0, "enabled": True}},
                      {"name": "y", "node": 2}]},
    # bench.toml
    "bus.url": {"bus.url": "modbus-tcp://127.0.0.1:5999"},
    "units.*": {"units.{name}": 20},
    "relays.*.coil": {"relays.{table}.coil": 7},
    "relays.M*.dwell_s": {"relays.{table}.dwell_s": 0.5},
    "meter.registers.*": {"meter.registers.{name}": 0x4C},
    "meter.poll": {"meter.poll": ["total_va", "va_l2"]},
    "levels.registers.*": {"levels.registers.{name}": 0x10},
    "sequence.period_s": {"sequence.period_s": 30.0, "sequence.stages": [
        {"start_s": 0.0, "end_s": 10.0, "on": ["M1"]},
        {"start_s": 10.0, "end_s": 30.0, "on": ["M2"]}]},
    "sequence.stages": {"sequence.stages": [
        {"start_s": 0.0, "end_s": 14.0, "on": ["M1", "M2"]},
        {"start_s": 14.0, "end_s": 28.0, "on": []}]},
    "emulator.meter_space": {"emulator.meter_space": [0, 0x60]},
    "plant.base.phases": {"{key}": ["L1", "L2"]},
    "plant.loads.*.phases": {"{key}": ["L1", "L2"]},
    "plant.disturbance.phases": {"{key}": ["L1", "L2"]},
    "faults.schedule": {"faults.schedule": ["drop@10", "delay@2-3:ms=300"]},
    "plant.loads.*.relay": {"plant.loads.{table}.relay": "M2"},
    "plant.disturbance.windows": {"plant.disturbance.windows": [[1.0, 2.0]]},
    "plant.resources.*.consumer": {"plant.resources.q1.consumer": "M2",
                                   "plant.resources.q2.consumer": "M1", "expect":
                                   {"plant.resources.q1.consumer": "M2"}},
    "plant.resources.*.supplier": {"plant.resources.q1.supplier": "P2",
                                   "plant.resources.q2.supplier": "P1",
                                   "relays.P1.dwell_s": 5.0, "expect":
                                   {"plant.resources.q1.supplier": "P2",
                                    "plant.resources.q2.supplier": "P1"}},
    "plant.resources.*.bounds": {"{key}": [40.0, 170.0]},
    "plant.resources.*.limits": {"{key}": [0.0, 300.0]},
    "plant.resources.q1.q0": {"plant.resources.q1.q0": 60.0},
    "safety.level_min": {"safety.level_min": 10.0},
}
#: keys the readers read that a user's file cannot change alone, and why (each is proven by
#: another case)
COUPLED = {
    # a load's model decides which other keys it has: a packaged load cannot change model
    # without keys the other model refuses; a new load of either model is proven below
    "plant.loads.*.model": "test_a_new_load_of_any_model_takes_effect",
}


def _special(key: str) -> dict[str, Any] | None:
    for pattern, keys in SPECIAL.items():
        if re.fullmatch(pattern.replace(".", r"\.").replace("*", "[^.]+"), key):
            head, _, name = key.rpartition(".")
            table = head.rpartition(".")[2]
            return {k.format(key=key, table=table, name=name): v for k, v in keys.items()}
    return None


def _coupled(key: str) -> bool:
    return any(re.fullmatch(p.replace(".", r"\.").replace("*", "[^.]+"), key) for p in COUPLED)


def print_config(capsys: pytest.CaptureFixture[str], app: str, *argv: str
                 ) -> dict[str, Any]:
    code = main([app, "run", "--print-config", "--json", *argv])
    out, err = capsys.readouterr()
    assert code == 0, err
    return json.loads(out)


def cases(settings: list[Setting]) -> list[Setting]:
    """The keys of the configs (``run.*`` are the options), but the coupled ones, which have
    their own test."""
    keys = [s for s in settings if not s.key.startswith("run.")]
    return [s for s in keys if not _coupled(s.key)]


def expected_value(key: str, value: Any, folder: Path) -> Any:
    if key in ("master.eds", "emulator.eds") or key.startswith("models."):
        return str(folder / value)
    return value


def written(setting: Setting, folder: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """The keys to write to set ``setting`` to another value, and the values expected."""
    keys = _special(setting.key)
    if keys is None:
        if setting.kind == "path" or setting.key.startswith("models."):
            keys = {setting.key: "elsewhere/my-file"}
        else:
            other = another(setting)
            assert other is not None, f"{setting.key}: no other value known for a " \
                f"{setting.kind} ({setting.rule}): add it to SPECIAL"
            keys = {setting.key: other}
    expect = keys.pop("expect", None) or {setting.key: keys[setting.key]}
    return keys, {k: expected_value(k, v, folder) for k, v in expect.items()}


@pytest.mark.parametrize("app, setting", [
    *(("servo", s) for s in cases(SERVO)), *(("bench", s) for s in cases(BENCH))],
    ids=lambda item: item if isinstance(item, str) else item.key)
def test_every_key_set_in_a_config_file_is_the_value_that_runs(tmp_path, capsys, app, setting):
    keys, expect = written(setting, tmp_path)
    config = tmp_path / "mine.toml"
    config.write_text(toml(keys))
    effective = print_config(capsys, app, "--config", str(config))
    for key, value in expect.items():
        assert effective[key] == {"value": value, "origin": f"--config {config}"}, key


#: every flag that sets a key: the key, the value the config file gives it, the flag's
#: arguments and the value that must run (a limit's flag only tightens)
KEY_FLAGS: dict[str, list[tuple[str, Any, list[str], Any]]] = {
    "servo": [
        ("master.node_id", 4, ["--node", "9"], 9),
        ("master.current_limit_mA", 800.0, ["--umax", "250"], 250.0),
        ("master.eds", "in-config.eds", ["--eds", "from-flag.eds"], "{cwd}/from-flag.eds"),
        ("bus.url", "virtual://bench-7", ["--drive", "socketcand://127.0.0.1:29999"],
         "socketcand://127.0.0.1:29999"),
        ("emulator.model", str(AXIS_MODEL), ["--drive", f"emulated?model={OTHER_AXIS_MODEL}"],
         str(OTHER_AXIS_MODEL)),
        ("safety.enabled", True, ["--safety", "enabled=true"], True),
        ("safety.following_error_deg", 40.0, ["--safety", "following_error_deg=20"], 20),
        ("safety.following_error_ms", 20.0, ["--safety", "following_error_ms=5"], 5),
        ("safety.position_min_deg", -1000.0, ["--safety", "position_min_deg=-500"], -500),
        ("safety.position_max_deg", 1000.0, ["--safety", "position_max_deg=500"], 500),
        ("safety.velocity_max_deg_s", 900.0, ["--safety", "velocity_max_deg_s=450"], 450),
        ("safety.stale_share_max", 0.4, ["--safety", "stale_share_max=0.2"], 0.2),
        ("safety.stale_window_ms", 100.0, ["--safety", "stale_window_ms=50"], 50),
    ],
    "bench": [
        ("bus.url", "modbus-tcp://127.0.0.1:5999", ["--bench", "emulated"], "emulated"),
        ("eec.hp_s", 20.0, ["--hp", "14"], 14),
        ("eec.hs_s", 2.0, ["--hs", "3"], 3),
        ("eec.gamma1", 0.5, ["--gamma1", "0.3"], 0.3),
        ("eec.gamma2", 0.5, ["--gamma2", "0.4"], 0.4),
        ("eec.terminal", "hold", ["--terminal", "none"], "none"),
        ("relays.P1.dwell_s", 6.0, ["--dwell", "9"], 9.0),
        ("relays.P2.dwell_s", 6.0, ["--dwell", "9"], 9.0),
        ("plant.disturbance.enabled", False, ["--disturbance"], True),
        ("safety.enabled", True, ["--safety", "enabled=true"], True),
        ("safety.max_total_va", 1000.0, ["--safety", "max_total_va=900"], 900),
        ("safety.max_total_va_ms", 400.0, ["--safety", "max_total_va_ms=100"], 100),
        ("safety.level_min", 10.0, ["--safety", "level_min=20"], 20),
        ("safety.level_max", 240.0, ["--safety", "level_max=200"], 200),
    ],
}
#: every flag that sets an option of the run (no key): its arguments, the option, its value
RUN_FLAGS: dict[str, list[tuple[list[str], str, Any]]] = {
    "servo": [
        (["--controller", "pid"], "run.controller", "pid"),
        (["--param", "kp=300"], "run.params", {"kp": 300}),
        (["--controller-budget", "0.1"], "run.controller_budget_s", 0.1),
        (["--limit", "rms_error_deg<=0.5"], "run.limits", ["rms_error_deg<=0.5"]),
        (["--can-log", "frames.asc"], "run.can_log", "frames.asc"),
        (["--reset-fault"], "run.reset_fault", True),
        (["--ert", "zoh"], "run.ert", "zoh"),
        (["--ht", "4"], "run.ht", 4),
        (["--hu", "5"], "run.hu", 5),
        (["--hp", "30"], "run.hp", 30),
        (["--umax", "600"], "run.umax", 600.0),
        (["--reference", "hold:position=5"], "run.reference", "hold:position=5"),
        (["--from-here"], "run.from_here", True),
        (["--home"], "run.home", True),
        (["--duration", "1.5"], "run.duration_s", 1.5),
        (["--settle", "0.25"], "run.settle_s", 0.25),
        (["--realtime"], "run.realtime", True),
        (["--quiet"], "run.quiet", True),
        (["--prediction-every", "3"], "run.prediction_every", 3),
        (["--out", "here.mcap"], "run.out", "here.mcap"),
        (["--axes", "x=1,y=2"], "run.axes", "x=1,y=2"),
        (["--allow-higher-current"], "run.allow_higher_current", True),
        (["--allow-looser-safety"], "run.allow_looser_safety", True),
    ],
    "bench": [
        (["--controller", "bc"], "run.controller", "bc"),
        (["--param", "gamma3=0.02"], "run.params", {"gamma3": 0.02}),
        (["--controller-budget", "0.5"], "run.controller_budget_s", 0.5),
        (["--limit", "J2_VA<=560"], "run.limits", ["J2_VA<=560"]),
        (["--cycles", "3"], "run.cycles", 3),
        (["--duration", "10"], "run.duration_s", 10.0),
        (["--realtime"], "run.realtime", True),
        (["--quiet"], "run.quiet", True),
        (["--out", "here.mcap"], "run.out", "here.mcap"),
        (["--allow-looser-safety"], "run.allow_looser_safety", True),
    ],
}
RECORDING_FLAGS = [
    (["--encoding", "json"], "run.recording.high_rate_encoding", "json"),
    (["--topic-encoding", "/events=json"], "run.recording.topic_encodings", {"/events": "json"}),
    (["--split-duration", "10"], "run.recording.split_duration_s", 10.0),
    (["--split-size", "5"], "run.recording.split_size_mb", 5.0),
    (["--live-rate", "/bench/power=5"], "run.recording.live_rates", {"/bench/power": 5.0}),
    (["--allow-remote-tuning"], "run.recording.live_remote_tuning", True),
]
#: flags that are not settings of the run: what to print, and where the config comes from
NOT_SETTINGS = {"--help", "--json", "--junit", "--print-config", "--config", "--live",
                # a labgrid place: it sets --bench / --drive (and --config, --node, --eds) as
                # its resource says, refusing a flag that says otherwise (tests/lab)
                "--place", "--coordinator", "--wait"}
#: flags that name a file of settings, each with its own test below
FILE_FLAGS = {"--params"}


@pytest.mark.parametrize("app, key, configured, argv, runs", [
    (app, *case) for app, rows in KEY_FLAGS.items() for case in rows],
    ids=lambda item: item if isinstance(item, str) else None)
def test_a_flag_overrides_the_config_file_key_by_key(tmp_path, capsys, monkeypatch, app, key,
                                                     configured, argv, runs):
    monkeypatch.chdir(tmp_path)
    config = tmp_path / "mine.toml"
    config.write_text(toml({key: configured}))
    before = print_config(capsys, app, "--config", str(config))
    assert before[key]["origin"] == f"--config {config}"
    after = print_config(capsys, app, "--config", str(config), *argv)
    if isinstance(runs, str):
        runs = runs.format(cwd=tmp_path)
    assert after[key] == {"value": runs, "origin": argv[0]}


@pytest.mark.parametrize("app, argv, key, runs", [
    *((app, *case) for app, rows in RUN_FLAGS.items() for case in rows),
    *((app, *case) for app in ("servo", "bench") for case in RECORDING_FLAGS)],
    ids=lambda item: item if isinstance(item, str) else None)
def test_a_flag_without_a_key_reaches_the_run(tmp_path, capsys, monkeypatch, app, argv, key,
                                              runs):
    monkeypatch.chdir(tmp_path)
    before = print_config(capsys, app)
    assert before[key]["value"] != runs
    after = print_config(capsys, app, *argv)
    assert after[key]["value"] == runs
    assert after[key]["origin"] == argv[0]


@pytest.mark.parametrize("app", ["servo", "bench"])
def test_every_flag_of_a_run_is_known_to_this_test(app):
    """A new flag must say which key or option it sets (above), or why it sets none."""
    parser = build_parser()
    run = parser._subparsers._group_actions[0].choices[app]  # type: ignore[union-attr]
    run = run._subparsers._group_actions[0].choices["run"]  # type: ignore[union-attr]
    flags = {a.option_strings[-1] for a in run._actions if a.option_strings}
    known = ({argv[0] for _, _, argv, _ in KEY_FLAGS[app]}
             | {argv[0] for argv, _, _ in RUN_FLAGS[app]}
             | {argv[0] for argv, _, _ in RECORDING_FLAGS} | NOT_SETTINGS | FILE_FLAGS)
    assert flags - known == set()


SHOWS_PARAMS = """
class ShowsParams:
    def __init__(self, *args):
        raise ValueError("params " + repr(sorted(args[-1].items())))
    def step(self, position_deg, t_s):
        return 0.0
    def decide(self, obs):
        return {}
"""


@pytest.mark.parametrize("app", ["servo", "bench"])
def test_params_from_a_file_sit_between_the_config_and_the_param_flags(tmp_path, capsys,
                                                                       monkeypatch, app):
    """defaults < packaged < --config's [controller] < --params F.toml < --param."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "shows.py").write_text(SHOWS_PARAMS)
    (tmp_path / "mine.toml").write_text("[controller]\na = 1\nb = 1\nc = 1\n")
    (tmp_path / "best.toml").write_text("b = 2\nc = 2\n")
    shown = print_config(capsys, app, "--controller", "shows.py:ShowsParams",
                         "--params", "best.toml")
    assert shown["run.params"] == {"value": {"b": 2, "c": 2}, "origin": "--params"}
    assert shown["run.params_file"] == {"value": "best.toml", "origin": "--params"}
    assert main([app, "run", "--controller", "shows.py:ShowsParams", "--config", "mine.toml",
                 "--params", "best.toml", "--param", "c=3"]) == 2
    assert "params [('a', 1), ('b', 2), ('c', 3)]" in capsys.readouterr().err
    (tmp_path / "bad.toml").write_text("gain = [1, 2]\n")
    assert main([app, "run", "--controller", "pid" if app == "servo" else "eec",
                 "--params", "bad.toml"]) == 2
    assert capsys.readouterr().err.strip().endswith(
        "bad.toml: gain: a parameter is a number, true/false or text (an axis' own in its "
        "[AXIS] table), got [1, 2]")


def test_every_key_of_the_packaged_configs_is_covered():
    """Every key is a case of the key-by-key test, or coupled to another that has a test."""
    for settings in (SERVO, BENCH):
        keys = [s.key for s in settings if not s.key.startswith("run.")]
        assert keys, "the readers read no key"
        for key in keys:
            assert key in {s.key for s in cases(settings)} or _coupled(key), key


def test_a_new_load_of_any_model_takes_effect(tmp_path, capsys):
    """A load's model decides its other keys: a new relay with a load of each built-in model,
    and one of a model file (its path beside the config file)."""
    s3 = types.SimpleNamespace(A=np.eye(1) * 0.5, B=np.ones((1, 1)), C=np.ones((1, 1)),
                               D=np.zeros((1, 1)), dt=0.01)
    (tmp_path / "s3.json").write_text(model_file_of(s3, ["/ident/relays:S3"],
                                                    ["/bench/power:va_l2"]))
    config = tmp_path / "loads.toml"
    config.write_text(toml({"relays.S1": {"coil": 5}, "relays.S2": {"coil": 6},
                            "relays.S3": {"coil": 7},
                            "plant.loads.S3": {"relay": "S3", "model": "s3.json", "pf": 0.5},
                            "plant.loads.S1": {"relay": "S1", "model": "first_order",
                                               "va": 50.0, "pf": 1.0, "tau_on_s": 0.1,
                                               "tau_off_s": 0.1},
                            "plant.loads.S2": {"relay": "S2", "model": "induction_motor",
                                               "va": 60.0, "inertia_h_s": 0.1, "circuit": {
                                                   "r1": 0.1, "x1": 0.25, "xm": 2.0,
                                                   "r2": 0.2, "x2": 0.25},
                                               "load_torque": {"t0": 0.05, "t2": 0.6}}}))
    effective = print_config(capsys, "bench", "--config", str(config))
    origin = f"--config {config}"
    assert effective["plant.loads.S1.model"] == {"value": "first_order", "origin": origin}
    assert effective["plant.loads.S2.model"] == {"value": "induction_motor", "origin": origin}
    assert effective["plant.loads.S2.circuit.xm"] == {"value": 2.0, "origin": origin}
    assert effective["plant.loads.S3.model"] == {"value": str(tmp_path / "s3.json"),
                                                 "origin": origin}
    assert effective["plant.loads.S3.pf"] == {"value": 0.5, "origin": origin}


def test_the_run_tables_and_the_bus_options_take_effect(tmp_path, capsys):
    """[controller], [limits] and [bus.options] are not in the packaged file: set, they run."""
    config = tmp_path / "drive.toml"
    config.write_text(toml({"bus.interface": "socketcand", "bus.options.host": "127.0.0.1",
                            "bus.options.port": 29999, "controller.kp": 250.0,
                            "limits.rms_error_deg": {"max": 0.5}}))
    effective = print_config(capsys, "servo", "--config", str(config))
    origin = f"--config {config}"
    assert effective["bus.url"] == {"value": "socketcand://127.0.0.1:29999/can0",
                                    "origin": origin}
    assert effective["bus.options.port"] == {"value": 29999, "origin": origin}
    assert effective["controller.kp"] == {"value": 250.0, "origin": origin}
    assert effective["limits.rms_error_deg.max"] == {"value": 0.5, "origin": origin}


@pytest.mark.parametrize("app, text, named", [
    ("servo", "[master]\ncurrent_limit_mA = \"300\"\n",
     "key 'master.current_limit_mA' must be a number, got a string '300'"),
    ("servo", "[safety]\nfollowing_error_deg = true\n",
     "key 'safety.following_error_deg' must be a number, got a boolean true"),
    ("bench", "[eec]\nhp_s = \"28\"\n", "key 'eec.hp_s' must be a number, got a string '28'"),
    ("bench", "[relays.P1]\ndwell_s = -1\n", "key 'relays.P1.dwell_s' must be >= 0 s, got -1 s"),
    ("servo", "[[axis]]\nname = \"x\"\nnode = 1\n[axis.safety]\nfollowing_error_deg = -1\n"
              "[[axis]]\nname = \"y\"\nnode = 2\n",
     "key 'axis[0].safety.following_error_deg' must be > 0 deg, got -1 deg"),
    ("servo", "[[axis]]\nname = \"x\"\nnode = 1\n[axis.safety]\nfollowing_error = 5\n"
              "[[axis]]\nname = \"y\"\nnode = 2\n",
     "unknown key 'axis[0].safety.following_error' (did you mean "
     "'axis[0].safety.following_error_ms'? known here: enabled, following_error_deg, "
     "following_error_ms, position_max_deg, position_min_deg, stale_share_max, "
     "stale_window_ms, velocity_max_deg_s)"),
])
def test_a_value_of_the_wrong_kind_is_one_line_naming_the_key(tmp_path, capsys, app, text,
                                                              named):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    code = main([app, "run", "--print-config", "--config", str(config)])
    err = capsys.readouterr().err
    assert code == 2 and err == f"hil: error: {config}: {named}\n"


def test_the_configuration_reference_is_generated_from_the_readers():
    """docs/CONFIGURATION.md is what `make docs` writes today: it cannot drift."""
    from hil.cli.config_reference import reference

    committed = (Path(__file__).parents[2] / "docs" / "CONFIGURATION.md").read_text()
    assert committed == reference(), "docs/CONFIGURATION.md is stale: run `make docs`"
    for setting in cases(SERVO) + cases(BENCH):
        named = "[[axis]]" if setting.key == "axis" else setting.key.rpartition(".")[2]
        assert f"`{named}`" in committed
