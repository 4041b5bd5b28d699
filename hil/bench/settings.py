"""A bench run's settings, resolved in one place, in one order for every key:

    built-in defaults < hil/configs/bench.toml and eec.toml < the user's --config < flags

Flags that set a key are layers over the files: ``--bench`` is ``bus.url``, ``--hp``,
``--hs``, ``--gamma1``, ``--gamma2`` and ``--terminal`` are keys of ``[eec]``, ``--dwell`` is
every peripheral's ``relays.NAME.dwell_s``, ``--disturbance`` is
``plant.disturbance.enabled``, ``--safety K=V`` is ``safety.K``. For the built-in ``eec``, the
config's ``[controller]`` table and ``--param`` are ``[eec]`` keys too, between the file's
``[eec]`` and those flags. What the run uses comes from :class:`BenchSettings` only, so what
``--print-config`` shows is what runs.

Limits only tighten from a flag: a ``--safety`` value looser than the configured one, or a
``--dwell`` shorter than a configured one, needs ``--allow-looser-safety`` and is then
recorded as a warning.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from hil.bench.config import BenchConfig, EecConfig, config_layers, parse_configs
from hil.bench.options import BenchRunOptions, flag_of
from hil.core.params import params_origin
from hil.core.settings import (
    LOWER,
    SWITCH,
    UPPER,
    Layer,
    Setting,
    effective,
    lay,
    loosened,
    option_settings,
    tightened_only,
)

#: the keys a flag sets (a ``*`` stands for any name; ``--dwell`` sets the peripherals'), for
#: the reference and --help; the layers themselves are built by :func:`resolve_bench`
FLAG_KEYS = {"bus.url": "--bench", "eec.hp_s": "--hp", "eec.hs_s": "--hs",
             "eec.gamma1": "--gamma1", "eec.gamma2": "--gamma2", "eec.terminal": "--terminal",
             "relays.P1.dwell_s": "--dwell", "relays.P2.dwell_s": "--dwell",
             "plant.disturbance.enabled": "--disturbance", "safety.*": "--safety KEY=VALUE"}
#: how each limit of ``[safety]`` tightens
SAFETY_DIRECTIONS = {"enabled": SWITCH, "max_total_va": UPPER, "max_total_va_ms": UPPER,
                     "level_min": LOWER, "level_max": UPPER}
#: the flags that set a key of ``[eec]``: option field -> key
EEC_FLAGS = {"hp_s": "hp_s", "hs_s": "hs_s", "gamma1": "gamma1", "gamma2": "gamma2",
             "terminal": "terminal"}
#: the options that land on a key of the configs (shown there), or are not the user's (a
#: program's overrides, the config file itself: the origins name it)
NOT_SETTINGS = ("bench", "hp_s", "hs_s", "gamma1", "gamma2", "terminal", "dwell_s",
                "disturbance", "seed", "safety", "overrides", "config_path")


@dataclass(frozen=True)
class BenchSettings:
    """Everything a bench run uses, resolved: the options, both configs with the flags laid in,
    where the bench is, and the warnings a loosened limit gives (event kind, message)."""

    options: BenchRunOptions
    bench: BenchConfig
    eec: EecConfig
    notices: tuple[tuple[str, str], ...] = ()

    @property
    def url(self) -> str:
        """Where the bench is (``bus.url``)."""
        return self.bench.bus.url

    def settings(self) -> list[Setting]:
        """Every setting as it runs, with its origin: the run's options, then the keys of
        bench.toml and eec.toml."""
        options = self.options
        defaults = BenchRunOptions(controller=options.controller)
        layered = self.bench.layered
        assert layered is not None
        named = options.controller if isinstance(options.controller, str) else None
        resolved = {"controller": (named or options.controller,
                                   "--controller" if named != "" else "not given"),
                    "params": (dict(options.params), "default" if not options.params
                               else params_origin(options.params, options.params_file))}
        return [*option_settings(options, defaults, resolved, NOT_SETTINGS, flag_of),
                *self.bench.settings(), *effective(self.eec.reads, layered)]


def resolve_bench(options: BenchRunOptions) -> BenchSettings:
    """The settings of a bench run (see the module); a UsageError names a flag that would
    loosen a limit without being allowed to, a ConfigError a bad key."""
    layers, text = config_layers(options.config_path)
    configured, _ = parse_configs(lay(layers), options.config_path, text)
    flags = _flag_layers(options, configured)
    bench, eec = parse_configs(lay([*layers, *flags]), options.config_path, text)
    notices = _loosened(options, configured, bench)
    return BenchSettings(options, bench, eec, tuple(notices))


def _flag_layers(options: BenchRunOptions, configured: BenchConfig) -> list[Layer]:
    """The flags (and program overrides) that set keys of the configs, in precedence order."""
    layers = []
    if options.overrides:
        layers.append(Layer("overrides", {"eec": dict(options.overrides)}))
    if options.controller == "eec":  # the built-in's params are [eec] keys
        if configured.run.params:
            layers.append(Layer("[controller]", {"eec": dict(configured.run.params)}))
        if options.params:
            layers.append(Layer("--param", {"eec": dict(options.params)}))
    for field, key in EEC_FLAGS.items():
        value = getattr(options, field)
        if value is not None:
            layers.append(Layer(f"--{field.removesuffix('_s')}", {"eec": {key: value}}))
    if options.bench is not None:
        layers.append(Layer("--bench", {"bus": {"url": options.bench}}))
    if options.dwell_s is not None:
        layers.append(Layer("--dwell", {"relays": {
            name: {"dwell_s": float(options.dwell_s)}
            for name in configured.problem.peripherals}}))
    if options.disturbance:
        layers.append(Layer("--disturbance", {"plant": {"disturbance": {"enabled": True}}}))
    if options.seed is not None:
        layers.append(Layer("--seed", {"plant": {"seed": options.seed}}))
    if options.safety:
        layers.append(Layer("--safety", {"safety": dict(options.safety)}))
    return layers


def _loosened(options: BenchRunOptions, configured: BenchConfig, bench: BenchConfig
              ) -> list[tuple[str, str]]:
    """``--safety`` and ``--dwell`` may tighten the configured limits; loosening needs
    ``--allow-looser-safety``."""
    looser = []
    if options.safety:
        after = {k: v for k, v in bench.data["safety"].items() if k in options.safety}
        looser += loosened(configured.data["safety"], after, SAFETY_DIRECTIONS)
    if options.dwell_s is not None:
        dwell = _dwell(bench)
        looser += loosened(_dwell(configured), dwell, dict.fromkeys(dwell, LOWER))
    flag = "--dwell" if looser and looser[0].startswith("relays.") else "--safety"
    return tightened_only(looser, flag, options.allow_looser_safety)


def _dwell(bench: BenchConfig) -> Mapping[str, Any]:
    return {f"relays.{name}.dwell_s": bench.problem.dwell_s[name]
            for name in bench.problem.peripherals}
