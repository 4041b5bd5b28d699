"""The relay bench's configuration, read once and strictly, in this one place.

``bench.toml`` (the packaged default with a user's file laid over it) and ``eec.toml`` become
frozen dataclasses here. Drivers, emulators and controllers define the small dataclasses they
need and receive them; none of them reads TOML. Every table is read with
:class:`hil.core.config.Table`: a misspelt key, a wrong type or a value out of range is one
:class:`~hil.errors.ConfigError` naming the file (``bench config`` / ``eec config`` for
the packaged defaults, the user's file when there is one) and the dotted key.

* :func:`load_bench_config` / :func:`parse_bench_config` -> :class:`BenchConfig`;
* :func:`load_configs` -> the bench and the EEC config of ``hil bench run`` (one user file may
  hold tables of both);
* :func:`check_emulation` - what the emulator needs beyond a real bench (a relay module with
  enough coils, meter quantities the plant computes, registers inside its served blocks),
  checked when an emulator is built, so a real bench is not held to the emulator's limits.
"""

from __future__ import annotations

import importlib.resources
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from hil.bench.safety import BenchSafety
from hil.controllers.bench.eec_choices import SOLVERS, TERMINALS
from hil.controllers.bench.kalman import KalmanSettings
from hil.controllers.bench.problem import BenchProblem, MachiningSequence, Resource, Stage
from hil.core.config import Table, deep_merge, load_toml, parse_toml
from hil.core.ranges import MAX_DURATION_S, MAX_DWELL_S, MAX_EEC_HORIZON_S
from hil.core.settings import KeyRead, Layer, Layered, Setting, effective, lay
from hil.core.verdict import RUN_TABLES, RunTables, read_run_tables
from hil.drivers.bench.modbus import BenchMap, BusSettings, RelaySpec, plan_reads
from hil.emulators.bench.load_model import LoadModel, load_load_model, period_problem
from hil.emulators.bench.plant import (
    METER_QUANTITIES,
    MODELS,
    PHASES,
    ConstantLoadSpec,
    DisturbanceSpec,
    FirstOrderLoadSpec,
    MeterSpec,
    ModelLoadSpec,
    MotorCircuit,
    MotorSpec,
    PlantSpec,
    ResourceSpec,
)
from hil.emulators.bench.server import UNKNOWN_UNIT_POLICIES, ServerSettings
from hil.emulators.errors import EmulatorSetupError
from hil.emulators.faults import Fault, for_emulator, parse_faults_table
from hil.errors import ConfigError

SOURCE = "bench config"
EEC_SOURCE = "eec config"
BENCH_TABLES = ("bus", "units", "relays", "meter", "levels", "sampling", "sequence", "safety",
                "emulator", "plant", "faults")
EEC_TABLES = ("eec", "kalman", "models")
UNIT_ROLES = ("relays", "meter", "levels")


@dataclass(frozen=True)
class SamplingSettings:
    """``[sampling]``: the sample period (the loop's base period) and the slower polls."""

    period_s: float
    levels_every: int            # poll the level sensors every N samples
    relays_readback_every: int   # read the coils back every N samples (0 = never)


@dataclass(frozen=True)
class BenchConfig:
    """``bench.toml`` read: what each side of the wire is given."""

    source: str                  # how errors name the file
    data: dict[str, Any]         # the merged TOML as read (recorded in sessions)
    user_text: str               # the user's file ('' without one)
    bus: BusSettings             # the driver's link and watchdog
    map: BenchMap                # units, relays, planned register reads
    sampling: SamplingSettings
    problem: BenchProblem        # sequence, resources, dwell: what the controllers know
    plant: PlantSpec             # the emulator's plant
    server: ServerSettings       # the emulator's Modbus server
    run: RunTables               # [controller] params and [limits] of a run
    safety: BenchSafety = field(default_factory=BenchSafety)  # [safety]: the run's limits
    faults: tuple[Fault, ...] = ()  # [faults]: what the emulator does wrong, and when
    layered: Layered | None = None  # the layers it was laid from
    reads: tuple[KeyRead, ...] = ()  # every key as read, in reading order

    def settings(self) -> list[Setting]:
        """Every key as it runs, with its origin."""
        return effective(self.reads, self.layered or lay([Layer(self.source, self.data)]))

    def with_dwell(self, dwell_s: float | None) -> BenchConfig:
        """Every peripheral's dwell set to ``dwell_s`` (``hil bench run --dwell``) for the
        controllers and the safety layer alike; None: as configured."""
        if dwell_s is None:
            return self
        dwell = float(dwell_s)
        if not 0 <= dwell <= MAX_DWELL_S:
            raise ConfigError(f"--dwell {dwell:g} s: must be 0..{MAX_DWELL_S:g} s")
        peripherals = self.problem.peripherals
        relays = {name: replace(spec, dwell_s=dwell) if name in peripherals else spec
                  for name, spec in self.map.relays.items()}
        data = deep_merge(self.data, {"relays": {n: {"dwell_s": dwell} for n in peripherals}})
        problem = replace(self.problem, dwell_s=dict.fromkeys(peripherals, dwell))
        return replace(self, data=data, map=replace(self.map, relays=relays), problem=problem)

    def emulator_tables(self) -> dict[str, Any]:
        """:attr:`data` for an emulator in another process: every load's model file made
        absolute (the tables are read from a temporary file, whose folder is not the
        config's)."""
        files = {name: spec.model.source for spec in self.plant.loads
                 if isinstance(spec, ModelLoadSpec) for name in spec.name.split("+")}
        if not files:
            return self.data
        return deep_merge(self.data, {"plant": {"loads": {
            name: {"model": path} for name, path in files.items()}}})

    def emulating(self, seed: int | None = None, disturbance: bool | None = None
                  ) -> BenchConfig:
        """The plant with its noise seed and disturbance switch overridden (None: as
        configured)."""
        plant = self.plant
        if seed is not None:
            plant = replace(plant, seed=seed)
        if disturbance is not None:
            plant = replace(plant, disturbance=replace(plant.disturbance, enabled=disturbance))
        return replace(self, plant=plant)


@dataclass(frozen=True)
class EecTable:
    """``[eec]`` as read; ``hil bench run``'s flags override some of it."""

    hp_s: float
    hs_s: float
    step_s: float
    gamma1: float
    gamma2: float
    gamma3: float
    terminal: str
    limit_va: float | None       # None: no contracted power term (limit_weight = 0)
    limit_weight: float
    feedback: bool
    peak_resolution_va: float
    time_limit_s: float
    mip_rel_gap: float
    solver: str


@dataclass(frozen=True)
class EecConfig:
    """``eec.toml`` read: the EEC's tuning, its Kalman filter, its model files."""

    source: str
    data: dict[str, Any]         # the merged TOML as read (recorded in sessions)
    eec: EecTable
    kalman: KalmanSettings
    models: dict[str, str]       # "machining" and each peripheral -> model file
    reads: tuple[KeyRead, ...] = ()  # every key as read, in reading order


# -- loading -------------------------------------------------------------------------------------


def default_text(name: str) -> str:
    """A packaged default config (``bench.toml``, ``eec.toml``): TOML text with its comments."""
    return importlib.resources.files("hil.configs").joinpath(name).read_text("utf-8")


def _default(name: str) -> dict[str, Any]:
    return parse_toml(default_text(name), f"hil/configs/{name}")


def config_layers(path: str | None = None) -> tuple[list[Layer], str]:
    """The packaged bench.toml and eec.toml and the user's file at ``path`` over both (one file
    may hold tables of both), as layers; and the user's text (``''`` without a file)."""
    packaged = str(importlib.resources.files("hil.configs"))
    layers = [Layer(f"hil/configs/{name}", _default(name), folder=packaged)
              for name in ("bench.toml", "eec.toml")]
    if path is None:
        return layers, ""
    user, text = load_toml(path)
    return [*layers, Layer(f"--config {path}", user,
                           folder=os.path.dirname(os.path.abspath(path)))], text


def load_bench_config(path: str | None = None) -> BenchConfig:
    """The default bench config with the file at ``path`` (if any) laid over it, read."""
    layers, text = config_layers(path)
    return parse_bench_config(lay(layers), path or SOURCE, text)


def load_configs(path: str | None = None, eec_overrides: Mapping[str, Any] | None = None
                 ) -> tuple[BenchConfig, EecConfig]:
    """The bench and the EEC config with the file at ``path`` (if any) laid over both;
    ``eec_overrides``: ``[eec]`` keys set by a program (benchmarks, tests)."""
    layers, text = config_layers(path)
    if eec_overrides:
        layers.append(Layer("overrides", {"eec": dict(eec_overrides)}))
    return parse_configs(lay(layers), path, text)


def parse_configs(layered: Layered, path: str | None, text: str
                  ) -> tuple[BenchConfig, EecConfig]:
    """The bench and the EEC config of ``layered`` (``path``: the user's file, if any)."""
    bench = parse_bench_config(layered, path or SOURCE, text)
    eec = parse_eec_config(layered, path or EEC_SOURCE, bench.problem.peripherals)
    step, period = eec.eec.step_s, bench.sampling.period_s
    divisor = round(step / period)
    if divisor < 1 or abs(divisor * period - step) > 1e-9:
        raise ConfigError(f"{eec.source}: key 'eec.step_s' = {step:g} is not a multiple of the "
                          f"sampling period {period:g} s")
    return bench, eec


# -- bench.toml ----------------------------------------------------------------------------------


def parse_bench_config(tables: Mapping[str, Any] | Layered, source: str = SOURCE,
                       user_text: str = "") -> BenchConfig:
    """Read a whole (merged) bench config, as tables or layers; the first problem found
    raises."""
    layered = tables if isinstance(tables, Layered) else lay([Layer(source, tables)])
    data = {name: value for name, value in layered.data.items() if name not in EEC_TABLES}
    top = Table(layered.data, source, layered=layered)
    relays = _relays(top.table("relays", required=True))
    units = _units(top.table("units", required=True))
    meter = top.table("meter", required=True)
    meter_registers = _registers(meter.table("registers", required=True))
    max_count = meter.integer("max_registers_per_request", 80)
    if not 2 <= max_count <= 125:
        raise meter.error("max_registers_per_request", f"must be 2..125, got {max_count}")
    max_gap = meter.integer("max_gap_registers", 8, at_least=0)
    poll = _poll(meter, meter_registers)
    meter.done()
    levels = top.table("levels", required=True)
    level_registers = _registers(levels.table("registers", required=True))
    levels.done()
    bench_map = BenchMap(units, relays,
                         plan_reads({q: meter_registers[q] for q in poll}, max_count, max_gap),
                         plan_reads(level_registers, max_count, max_gap))
    bus = _bus(top.table("bus", required=True))
    sampling = _sampling(top.table("sampling", required=True))
    sequence = _sequence(top.table("sequence", required=True), relays)
    _check_sequence_dwell(sequence, relays, source)
    safety = _safety(top.table("safety", required=True))
    plant_table = top.table("plant", required=True)
    resources = _resources(plant_table.table("resources", required=True), sequence, relays)
    problem = BenchProblem(sequence, tuple(
        Resource(r.name, r.consumer, r.supplier, r.alpha, r.eta, *r.bounds, r.q0)
        for r in resources), {r.supplier: relays[r.supplier].dwell_s for r in resources})
    emulator = top.table("emulator")
    plant = _plant(plant_table, emulator.integer("coils", 8, at_least=1), relays, resources)
    server = ServerSettings(units, meter_registers, _meter_space(emulator), max_count,
                            level_registers,
                            emulator.string("unknown_unit", "auto", choices=UNKNOWN_UNIT_POLICIES))
    emulator.done()
    run = read_run_tables(top)
    faults_table = top.table("faults")
    schedule = faults_table.array("schedule", [], "faults KIND@START[-END][:KEY=VALUE,...] or "
                                  "inline tables (docs/FAULTS.md)")
    faults_table.done()
    faults = tuple(parse_faults_table({"schedule": schedule}, source))
    for name in EEC_TABLES:  # one user file may hold the EEC's tables too
        top.raw(name, None)
    top.done()
    return BenchConfig(source, data, user_text, bus, bench_map, sampling, problem, plant,
                       server, run, safety,
                       tuple(for_emulator(faults, "bench", f"{source}: faults")), layered,
                       tuple(top.reads))


def _relays(table: Table) -> dict[str, RelaySpec]:
    if not table.names():
        raise ConfigError(f"{table.source}: [relays] is empty: name at least one relay")
    relays: dict[str, RelaySpec] = {}
    for name in table.names():
        relay = table.table(name)
        coil = relay.integer("coil")
        if coil < 0:
            raise relay.error("coil", f"is {coil}: a coil must be >= 0")
        dwell = relay.number("dwell_s", 5.0, at_least=0, at_most=MAX_DWELL_S)
        clash = next((r.name for r in relays.values() if r.coil == coil), None)
        if clash:
            raise ConfigError(f"{table.source}: relays {clash} and {name} are both on coil {coil}")
        relays[name] = RelaySpec(name, coil, relay.boolean("safe", False), dwell)
        relay.done()
    table.done()
    return relays


def _units(table: Table) -> dict[str, int]:
    units = {}
    for role in UNIT_ROLES:
        unit = units[role] = table.integer(role)
        if not 1 <= unit <= 247:
            raise table.error(role, f"must be 1..247, got {unit}")
    table.done()
    if len(set(units.values())) != len(units):
        raise ConfigError(f"{table.source}: [units] must give three different unit ids, "
                          f"got {units}")
    return units


def _registers(table: Table) -> dict[str, int]:
    """``{quantity: first register}`` of float32 values: 0..65534, no two overlapping."""
    if not table.names():
        raise ConfigError(f"{table.source}: [{table.path}] is empty")
    out: dict[str, int] = {}
    for name in table.names():
        address = table.integer(name)
        if not 0 <= address <= 0xFFFE:
            raise table.error(name, f"must be a register 0..65534, got {address}")
        clash = next((n for n, a in out.items() if abs(a - address) < 2), None)
        if clash:
            raise ConfigError(f"{table.source}: '{table.key(name)}' (register {address:#06x}) "
                              f"overlaps '{table.key(clash)}' (float32 values take two "
                              "registers)")
        out[name] = address
    table.done()
    return out


def _poll(meter: Table, registers: Mapping[str, int]) -> list[str]:
    poll = meter.array("poll", None, "names of [meter.registers]")
    if poll is None:
        return list(registers)
    unknown = [q for q in poll if not isinstance(q, str) or q not in registers]
    if unknown or not poll:
        raise meter.error("poll", f"must name registers of [meter.registers], unknown: "
                                  f"{unknown}")
    return list(poll)


def _bus(table: Table) -> BusSettings:
    bus = BusSettings(
        url=table.string("url"),
        timeout_s=table.number("timeout_s", above=0),
        attempts=table.integer("attempts", at_least=1),
        reconnect_interval_s=table.number("reconnect_interval_s", above=0),
        watchdog_polls=table.integer("watchdog_polls", at_least=1),
        give_up_s=table.number("give_up_s", 30.0, at_least=0),
        lockstep_timeout_s=table.number("lockstep_timeout_s", 10.0, above=0),
    )
    table.done()
    return bus


def _sampling(table: Table) -> SamplingSettings:
    sampling = SamplingSettings(
        period_s=table.number("period_s", at_least=1e-3, at_most=60.0),
        levels_every=table.integer("levels_every", 1, at_least=1),
        relays_readback_every=table.integer("relays_readback_every", 100, at_least=0),
    )
    table.done()
    return sampling


def _safety(s: Table) -> BenchSafety:
    """``[safety]``: positive limits, the level range ordered."""
    safety = BenchSafety(
        enabled=s.boolean("enabled"),
        max_total_va=s.number("max_total_va", above=0),
        max_total_va_ms=s.number("max_total_va_ms", at_least=0, at_most=60_000),
        level_min=s.number("level_min"),
        level_max=s.number("level_max"),
    )
    if not safety.level_min < safety.level_max:
        raise s.error("level_max", f"must be above level_min ({safety.level_min:g}), got "
                      f"{safety.level_max:g}")
    s.done()
    return safety


def _sequence(table: Table, relays: Mapping[str, RelaySpec]) -> MachiningSequence:
    """Stages tiling ``[0, period_s)`` in order, each naming relays of ``[relays]``."""
    period = table.number("period_s", above=0, at_most=MAX_DURATION_S)
    raw = table.array("stages", rule="stages {start_s, end_s, on} tiling [0, period_s)")
    if not raw:
        raise table.error("stages", "must list at least one stage")
    table.done()
    stages: list[Stage] = []
    expected_start = 0.0
    for i, entry in enumerate(raw):
        where = f"{table.source}: sequence.stages[{i}]"
        if not isinstance(entry, Mapping):
            raise ConfigError(f"{where} must be a table {{start_s, end_s, on}}")
        stage = Table(entry, where)
        start, end = stage.number("start_s"), stage.number("end_s")
        on = stage.get("on", list)
        stage.done()
        if abs(start - expected_start) > 1e-9 or not end > start:
            raise ConfigError(f"{where}: stages must tile [0, period) in order: expected "
                              f"start_s = {expected_start:g} < end_s, got {start:g}..{end:g}")
        unknown = [n for n in on if not isinstance(n, str) or n not in relays]
        if unknown:
            raise ConfigError(f"{where}: unknown relay(s) {unknown} (relays: "
                              f"{', '.join(relays)})")
        stages.append(Stage(start, end, frozenset(on)))
        expected_start = end
    if abs(expected_start - period) > 1e-9:
        raise ConfigError(f"{table.source}: sequence stages end at {expected_start:g} s, "
                          f"not at period_s = {period:g} s")
    names = tuple(sorted(set().union(*(stage.on for stage in stages))))
    return MachiningSequence(period, tuple(stages), names)


def _check_sequence_dwell(sequence: MachiningSequence, relays: Mapping[str, RelaySpec],
                          source: str) -> None:
    """A relay the sequence plays must be able to follow it: its dwell shorter than the
    shortest time the sequence holds it on or off (the safety layer would defer the rest)."""
    for name in sequence.relays:
        holds = _holds(sequence, name)
        if relays[name].dwell_s >= min(holds):
            raise ConfigError(
                f"{source}: relays.{name}.dwell_s = {relays[name].dwell_s:g} s is not shorter "
                f"than the shortest time the sequence holds {name} on or off ({min(holds):g} "
                "s): the relay could not follow the sequence")


def _holds(sequence: MachiningSequence, name: str) -> list[float]:
    """How long the (periodic) sequence holds relay ``name`` in each state, in turn."""
    runs: list[list[Any]] = []  # [state, seconds]
    for stage in sequence.stages:
        on = name in stage.on
        if runs and runs[-1][0] == on:
            runs[-1][1] += stage.end_s - stage.start_s
        else:
            runs.append([on, stage.end_s - stage.start_s])
    if len(runs) > 1 and runs[0][0] == runs[-1][0]:  # the period wraps around
        runs[0][1] += runs.pop()[1]
    return [seconds for _, seconds in runs]


def _relay(table: Table, key: str, relays: Mapping[str, RelaySpec]) -> str:
    name = table.string(key)
    if name not in relays:
        raise table.error(key, f"names relay {name!r}, not in [relays] ({', '.join(relays)})")
    return name


def _pair(table: Table, key: str) -> tuple[float, float]:
    value = table.array(key, rule="[low, high], low < high")
    ok = (len(value) == 2 and all(_is_number(x) for x in value) and value[0] < value[1])
    if not ok:
        raise table.error(key, f"must be [low, high] with low < high, got {value!r}")
    return float(value[0]), float(value[1])


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _resources(table: Table, sequence: MachiningSequence, relays: Mapping[str, RelaySpec]
               ) -> list[ResourceSpec]:
    """``[plant.resources]``: the controllers' q_j (eq. 10, Table I) and the plant's tanks."""
    out = []
    for name in table.names():
        res = table.table(name)
        consumer, supplier = _relay(res, "consumer", relays), _relay(res, "supplier", relays)
        if consumer not in sequence.relays:
            raise res.error("consumer", f"= {consumer!r} is not a relay of the machining "
                                        f"sequence ({', '.join(sequence.relays)})")
        if supplier in sequence.relays:
            raise res.error("supplier", f"= {supplier!r} is a machining relay; a supplier "
                                        "must be a peripheral")
        out.append(ResourceSpec(
            name, consumer, supplier, alpha=res.number("alpha"), eta=res.number("eta", above=0),
            q0=res.number("q0"), bounds=_pair(res, "bounds"), limits=_pair(res, "limits"),
            sigma=res.number("sigma", 0.0, at_least=0)))
        res.done()
    table.done()
    if not out:
        raise ConfigError(f"{table.source}: [plant.resources] is empty: the controllers need q_j")
    suppliers = [r.supplier for r in out]
    if len(set(suppliers)) != len(suppliers):
        raise ConfigError(f"{table.source}: each peripheral may supply one resource only")
    return out


# -- the plant (emulator only: a real bench ignores it) -------------------------------------------


def _phases(table: Table, key: str = "phases") -> tuple[str, ...]:
    phases = table.array(key, ["L2"], f"distinct phases among {', '.join(PHASES)}")
    if not phases or not all(p in PHASES for p in phases) or len(set(phases)) != len(phases):
        raise table.error(key, f"must list distinct phases among {list(PHASES)}, got {phases!r}")
    return tuple(phases)


def _power_factor(table: Table, key: str, default: float | None = None) -> float:
    if default is None:
        return table.number(key, above=0.0, at_most=1.0)
    return table.number(key, default, above=0.0, at_most=1.0)


def _plant(table: Table, coils: int, relays: Mapping[str, RelaySpec],
           resources: list[ResourceSpec]) -> PlantSpec:
    dt = table.number("dt_s", above=0)
    seed = table.integer("seed", 0, at_least=0)  # numpy's generators take none below 0
    meter_table = table.table("meter", required=True)
    meter = MeterSpec(
        voltage_v=meter_table.number("voltage_v", above=0),
        voltage_sigma_v=meter_table.number("voltage_sigma_v", 0.0, at_least=0),
        va_sigma=meter_table.number("va_sigma", 0.0, at_least=0),
        frequency_hz=meter_table.number("frequency_hz", above=0),
        import_kwh=meter_table.number("import_kwh", 0.0),
    )
    meter_table.done()
    base_table = table.table("base", required=True)
    base = ConstantLoadSpec(base_table.number("va", above=0), _power_factor(base_table, "pf"),
                            _phases(base_table))
    base_table.done()
    loads_table = table.table("loads")
    read = [_load(loads_table.table(name), name, relays) for name in loads_table.names()]
    loads = _with_model_loads(read, dt)
    loads_table.done()
    disturbance = _disturbance(table.table("disturbance"))
    table.done()
    return PlantSpec(dt, seed, coils, {name: r.coil for name, r in relays.items()}, meter, base,
                     loads, disturbance, tuple(resources))


@dataclass(frozen=True)
class _ModelFileLoad:
    """A load whose table names a model file, as read (its table: for errors)."""

    name: str
    relay: str
    model: LoadModel
    pf: float
    phases: tuple[str, ...]
    table: Table


#: the keys of a built-in load model, unused when the load is a model file
_BUILT_IN_KEYS = ("va", "tau_on_s", "tau_off_s", "inertia_h_s", "circuit", "load_torque")


def _load(table: Table, name: str, relays: Mapping[str, RelaySpec]
          ) -> FirstOrderLoadSpec | MotorSpec | _ModelFileLoad:
    relay = _relay(table, "relay", relays)
    phases = _phases(table)
    given = table.data.get("model")
    if isinstance(given, str) and given not in MODELS:
        return _model_file_load(table, name, relay, phases)
    model = table.string("model", choices=MODELS)
    load: FirstOrderLoadSpec | MotorSpec
    if model == "first_order":
        load = FirstOrderLoadSpec(
            name, relay, table.number("va", above=0), _power_factor(table, "pf"),
            table.number("tau_on_s", above=0), table.number("tau_off_s", above=0), phases)
    else:
        circuit = table.table("circuit", required=True)
        torque = table.table("load_torque", required=True)
        load = MotorSpec(
            name, relay, table.number("va", above=0), table.number("inertia_h_s", above=0),
            MotorCircuit(*(circuit.number(p, above=0) for p in ("r1", "x1", "xm", "r2", "x2"))),
            torque.number("t0", above=0), torque.number("t2", above=0), phases)
        circuit.done()
        torque.done()
    table.done()
    return load


def _model_file_load(table: Table, name: str, relay: str, phases: tuple[str, ...]
                     ) -> _ModelFileLoad:
    """``model = "F.json"``: the load's S from a model file (its path from the folder of the
    config file that names it), at power factor ``pf`` (default 1); a built-in model's keys
    (from the packaged table) are left unused."""
    path = table.file_path("model")
    try:
        model = load_load_model(path)
    except EmulatorSetupError as exc:
        raise table.error("model", f"is neither {' nor '.join(MODELS)} nor a load model: "
                          f"{exc}") from None
    pf = _power_factor(table, "pf", 1.0)
    for key in _BUILT_IN_KEYS:
        table.raw(key, None)
    table.done()
    return _ModelFileLoad(name, relay, model, pf, phases, table)


def _with_model_loads(read: list[FirstOrderLoadSpec | MotorSpec | _ModelFileLoad], dt: float
                      ) -> tuple[FirstOrderLoadSpec | MotorSpec | ModelLoadSpec, ...]:
    """The loads, those naming one model file as one load where the first of them is: the
    file's inputs read exactly their relays (the machining model reads M1 and M2: both tables
    name it), its period is the plant's step; it takes the first load's pf and phases."""
    groups: dict[str, list[_ModelFileLoad]] = {}
    for load in read:
        if isinstance(load, _ModelFileLoad):
            groups.setdefault(load.model.source, []).append(load)
    loads: list[FirstOrderLoadSpec | MotorSpec | ModelLoadSpec] = []
    for load in read:
        if not isinstance(load, _ModelFileLoad):
            loads.append(load)
            continue
        group = groups[load.model.source]
        if load is not group[0]:
            continue
        model, table = load.model, load.table
        problem = period_problem(model, dt)
        if problem is not None:
            raise table.error("model", f"({model.source}) does not fit the plant: {problem}")
        behind = {other.relay: other for other in group}
        for relay in model.relays:
            if relay not in behind:
                raise table.error("model", f"({model.source}) reads relay {relay!r}, and no "
                                  "load behind it names this file: name it in that load's table "
                                  "too (a model stands for every load it reads), or give this "
                                  "load a model of its own relay")
        for other in group:
            if other.relay not in model.relays:
                raise other.table.error("model", f"({model.source}) has no input of relay "
                                        f"{other.relay!r} (its relays: "
                                        f"{', '.join(model.relays)})")
        loads.append(ModelLoadSpec("+".join(other.name for other in group), model, load.pf,
                                   load.phases))
    return tuple(loads)


def _disturbance(table: Table) -> DisturbanceSpec:
    windows = []
    for window in table.array("windows", [], "[start_s, end_s] pairs"):
        ok = (isinstance(window, list) and len(window) == 2
              and all(_is_number(x) for x in window) and 0 <= window[0] < window[1])
        if not ok:
            raise table.error("windows", f"must hold [start_s, end_s] pairs with 0 <= start < "
                                         f"end, got {window!r}")
        windows.append((float(window[0]), float(window[1])))
    spec = DisturbanceSpec(
        enabled=table.boolean("enabled", False), va=table.number("va", 70.0, above=0),
        pf=_power_factor(table, "pf", 0.8), tau_s=table.number("tau_s", 0.05, above=0),
        phases=_phases(table), period_s=table.number("period_s", 0.0, at_least=0),
        windows=tuple(windows))
    table.done()
    return spec


def _meter_space(table: Table) -> tuple[int, int]:
    space = table.array("meter_space", rule="[first, end], 0 <= first < end")
    if len(space) != 2 or not all(isinstance(x, int) and not isinstance(x, bool) for x in space) \
            or not 0 <= space[0] < space[1]:
        raise table.error("meter_space", f"must be [first, end] with 0 <= first < end, got "
                                         f"{space!r}")
    return space[0], space[1]


def check_emulation(config: BenchConfig) -> None:
    """What an emulated bench needs beyond a real one; a ConfigError names the first miss."""
    source, plant, server = config.source, config.plant, config.server
    top_coil = max(plant.relays.values())
    if top_coil >= plant.coils:
        raise ConfigError(f"{source}: a relay uses coil {top_coil} but the relay module has "
                          f"{plant.coils} coils (emulator.coils)")
    unknown = [q for q in server.meter_registers if q not in METER_QUANTITIES]
    if unknown:
        raise ConfigError(f"{source}: key 'meter.registers.{unknown[0]}' is not a quantity the "
                          f"meter provides (known: {', '.join(METER_QUANTITIES)})")
    levels = server.level_registers
    missing = set(levels) - {r.name for r in plant.resources}
    if missing:
        raise ConfigError(f"{source}: [levels.registers] names {sorted(missing)} but the "
                          f"plant has resources {[r.name for r in plant.resources]}")
    blocks = ((server.meter_registers, server.meter_space),
              (levels, (min(levels.values()), max(levels.values()) + 2)))
    for addresses, (first, end) in blocks:
        for name, address in addresses.items():
            if not first <= address or address + 2 > end or (address - first) % 2:
                raise ConfigError(f"{source}: register {address:#06x} of {name} is outside the "
                                  f"served block [{first:#06x}, {end:#06x}) or not on a float "
                                  "boundary")


# -- eec.toml ------------------------------------------------------------------------------------


def parse_eec_config(tables: Mapping[str, Any] | Layered, source: str,
                     peripherals: tuple[str, ...]) -> EecConfig:
    """Read a whole (merged) EEC config, as tables or layers; model files are found from the
    folder of the file that names them (the packaged ones next to eec.toml)."""
    layered = tables if isinstance(tables, Layered) else lay([Layer(source, tables)])
    data = {name: value for name, value in layered.data.items() if name in EEC_TABLES}
    top = Table(layered.data, source, layered=layered)
    eec = _eec(top.table("eec", required=True))
    kalman_table = top.table("kalman")
    defaults = KalmanSettings()
    kalman = KalmanSettings(
        model_sigma=kalman_table.number("model_sigma", defaults.model_sigma, at_least=0),
        disturbance_sigma=kalman_table.number("disturbance_sigma", defaults.disturbance_sigma,
                                              at_least=0),
        meter_sigma=kalman_table.number("meter_sigma", defaults.meter_sigma, above=0),
    )
    kalman_table.done()
    models_table = top.table("models", required=True)
    models = {name: models_table.file_path(name) for name in ("machining", *peripherals)}
    models_table.done()
    for name in (*BENCH_TABLES, *RUN_TABLES):  # one file may hold the bench's tables too
        top.raw(name, None)
    top.done()
    return EecConfig(source, data, eec, kalman, models, tuple(top.reads))


def _eec(table: Table) -> EecTable:
    weight = table.number("limit_weight", 10.0, at_least=0)
    limit: float | None = table.number("limit_va", None, above=0)
    if weight > 0 and limit is None:
        raise ConfigError(f"{table.source}: missing key 'eec.limit_va' (needed while "
                          "eec.limit_weight > 0)")
    eec = EecTable(
        hp_s=table.number("hp_s", above=0, at_most=MAX_EEC_HORIZON_S),
        hs_s=table.number("hs_s", above=0),
        step_s=table.number("step_s", 1.0, above=0),
        gamma1=table.number("gamma1", at_least=0),
        gamma2=table.number("gamma2", at_least=0),
        gamma3=table.number("gamma3", 0.0, at_least=0),
        terminal=table.string("terminal", "hold", choices=TERMINALS),
        limit_va=limit if weight > 0 else None,
        limit_weight=weight,
        feedback=table.boolean("feedback", True),
        peak_resolution_va=table.number("peak_resolution_va", 1.0, at_least=0),
        time_limit_s=table.number("time_limit_s", 0.5, above=0, at_most=3600),
        mip_rel_gap=table.number("mip_rel_gap", 1e-4, at_least=0),
        solver=table.string("solver", "dp", choices=SOLVERS),
    )
    table.done()
    return eec
