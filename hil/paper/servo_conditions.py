"""The servo paper's conditions (``hil/configs/paper_servo.toml``), read strictly into one
frozen dataclass: what ``hil paper servo`` runs, every key used or refused.

``--quick`` lays the file's ``[quick]`` table over the rest: fewer horizons, shorter runs, the
explicit MPC at H_t = H_u = 2 (its build takes a third of a second instead of three).
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources

from hil.core.config import Table, parse_toml

SOURCE = "hil/configs/paper_servo.toml"


@dataclass(frozen=True)
class SineCase:
    """One sine reference of Figs. 5-10 with the current limit it runs at [mA]."""

    frequency_hz: float
    limit_ma: float

    @property
    def name(self) -> str:
        return f"{self.frequency_hz:g}hz-{self.limit_ma:g}ma"

    @property
    def title(self) -> str:
        return f"{self.frequency_hz:g} Hz, ±{self.limit_ma:g} mA"


@dataclass(frozen=True)
class ServoConditions:
    """Everything the reproduction runs at (units in the names)."""

    quick: bool
    cycle_period_us: int
    limit_ma: float
    rated_ma: float
    hp: int
    q: float
    r: float
    horizons: tuple[int, ...]
    fig5_ht: int
    waterfall_ht: int
    empc_ht: int
    empc_horizons: tuple[int, ...]
    amplitude_deg: float
    frequencies_hz: tuple[float, ...]
    settle_s: float
    cycles: float
    stroke_deg: float
    speed_rpm: float
    acceleration_deg_s2: float
    trapezoid_duration_s: float
    torque_ma: float
    push_start_s: float
    push_end_s: float
    disturbance_duration_s: float
    k_pos_rpm_per_deg: float
    k_vel_a_per_rpm: float
    ti_us: float
    sweep_r: tuple[float, ...]
    sweep_current_ma: tuple[float, ...]
    sweep_vff: tuple[float, ...]
    sweep_box_scale: tuple[float, ...]
    sweep_push_start_s: tuple[float, ...]
    sweep_friction_tau_s: tuple[float, ...]

    @property
    def sine_cases(self) -> tuple[SineCase, ...]:
        """Each frequency at the paper's limit, and the fastest also at the rated current."""
        cases = [SineCase(f, self.limit_ma) for f in self.frequencies_hz]
        return (*cases, SineCase(max(self.frequencies_hz), self.rated_ma))

    @property
    def fast(self) -> SineCase:
        """The 10 Hz case of Figs. 5, 6, 9 and 10, at the rated current (it fits no less)."""
        return SineCase(max(self.frequencies_hz), self.rated_ma)

    def sine_spec(self, frequency_hz: float) -> str:
        return f"sine:amplitude={self.amplitude_deg:g},frequency={frequency_hz:g}"

    def sine_duration_s(self, frequency_hz: float) -> float:
        return self.settle_s + self.cycles / frequency_hz

    @property
    def trapezoid_spec(self) -> str:
        return (f"trapezoid:stroke={self.stroke_deg:g},speed={self.speed_rpm:g},"
                f"acceleration={self.acceleration_deg_s2:g}")

    @property
    def disturbance_spec(self) -> str:
        return self.push_spec(self.push_start_s)

    def push_spec(self, start_s: float) -> str:
        """The disturbance scenario with the push starting at ``start_s``."""
        return f"disturbance:torque={self.torque_ma:g},start={start_s:g},end={self.push_end_s:g}"

    @property
    def pid_params(self) -> dict[str, float]:
        """Table I as the built-in PID's params."""
        return {"kp": self.k_pos_rpm_per_deg, "kv": self.k_vel_a_per_rpm, "ti_us": self.ti_us}


def load_conditions(quick: bool = False, text: str | None = None) -> ServoConditions:
    """The packaged conditions (or ``text``, a file of the same keys), ``[quick]`` laid over
    them when ``quick``. A wrong key is a ConfigError naming it."""
    if text is None:
        text = resources.files("hil.configs").joinpath("paper_servo.toml").read_text("utf-8")
    top = Table(parse_toml(text, SOURCE), SOURCE)
    drive, mpc, sine = top.table("drive"), top.table("mpc"), top.table("sine")
    trapezoid, push, pid = top.table("trapezoid"), top.table("disturbance"), top.table("pid")
    explain, fast = top.table("explain"), top.table("quick")
    values = {
        "cycle_period_us": drive.integer("cycle_period_us", choices=(500,)),
        "limit_ma": drive.number("current_limit_mA", above=0),
        "rated_ma": drive.number("rated_current_mA", above=0),
        "hp": mpc.integer("hp", at_least=2, at_most=200),
        "q": mpc.number("q", above=0),
        "r": mpc.number("r", above=0),
        "horizons": _integers(mpc, "horizons"),
        "fig5_ht": mpc.integer("fig5_ht", at_least=2),
        "waterfall_ht": mpc.integer("waterfall_ht", at_least=2),
        "empc_ht": mpc.integer("empc_ht", at_least=2, at_most=6),
        "empc_horizons": _integers(mpc, "empc_horizons", at_most=6),
        "amplitude_deg": sine.number("amplitude_deg", above=0),
        "frequencies_hz": _numbers(sine, "frequencies_hz"),
        "settle_s": sine.number("settle_s", at_least=0),
        "cycles": sine.number("cycles", above=0),
        "stroke_deg": trapezoid.number("stroke_deg", above=0),
        "speed_rpm": trapezoid.number("speed_rpm", above=0),
        "acceleration_deg_s2": trapezoid.number("acceleration_deg_s2", above=0),
        "trapezoid_duration_s": trapezoid.number("duration_s", above=0),
        "torque_ma": push.number("torque_mA", above=0),
        "push_start_s": push.number("start_s", at_least=0),
        "push_end_s": push.number("end_s", above=0),
        "disturbance_duration_s": push.number("duration_s", above=0),
        "k_pos_rpm_per_deg": pid.number("k_pos_rpm_per_deg", above=0),
        "k_vel_a_per_rpm": pid.number("k_vel_a_per_rpm", above=0),
        "ti_us": pid.number("ti_us", above=0),
        "sweep_r": _numbers(explain, "r"),
        "sweep_current_ma": _numbers(explain, "current_mA"),
        "sweep_vff": _numbers(explain, "vff", at_most=1.0, at_least=0.0),
        "sweep_box_scale": _numbers(explain, "box_scale"),
        "sweep_push_start_s": _numbers(explain, "push_start_s", at_least=0.0),
        "sweep_friction_tau_s": _numbers(explain, "friction_tau_s"),
    }
    shorter = {
        "horizons": _integers(fast, "horizons"),
        "fig5_ht": fast.integer("fig5_ht", at_least=2),
        "waterfall_ht": fast.integer("waterfall_ht", at_least=2),
        "empc_ht": fast.integer("empc_ht", at_least=2, at_most=6),
        "empc_horizons": _integers(fast, "empc_horizons", at_most=6),
        "settle_s": fast.number("settle_s", at_least=0),
        "cycles": fast.number("cycles", above=0),
        "trapezoid_duration_s": fast.number("trapezoid_duration_s", above=0),
        "disturbance_duration_s": fast.number("disturbance_duration_s", above=0),
        "sweep_r": _numbers(fast, "r"),
        "sweep_current_ma": _numbers(fast, "current_mA"),
        "sweep_vff": _numbers(fast, "vff", at_most=1.0, at_least=0.0),
        "sweep_box_scale": _numbers(fast, "box_scale"),
        "sweep_push_start_s": _numbers(fast, "push_start_s", at_least=0.0),
        "sweep_friction_tau_s": _numbers(fast, "friction_tau_s"),
    }
    for table in (drive, mpc, sine, trapezoid, push, pid, explain, fast, top):
        table.done()
    if quick:
        values.update(shorter)
    conditions = ServoConditions(quick=quick, **values)  # type: ignore[arg-type]
    _check(conditions, top)
    return conditions


def _check(c: ServoConditions, top: Table) -> None:
    """What the keys must agree on: horizons within H_p, the paper's cases among the runs."""
    if 1 not in c.horizons or max(c.horizons) > c.hp:
        raise top.error("mpc.horizons", f"must hold 1 (set-point tracking, what Figs. 7-8 are "
                        f"normalised to) and stay within mpc.hp ({c.hp})")
    for name, value in (("mpc.fig5_ht", c.fig5_ht), ("mpc.waterfall_ht", c.waterfall_ht)):
        if value not in c.horizons:
            raise top.error(name, f"({value}) must be one of mpc.horizons ({list(c.horizons)})")
    if c.empc_ht not in c.empc_horizons:
        raise top.error("mpc.empc_ht", f"({c.empc_ht}) must be one of mpc.empc_horizons")
    if not c.push_start_s < c.push_end_s < c.disturbance_duration_s:
        raise top.error("disturbance.end_s", "must lie after start_s and before duration_s")
    if not all(start < c.push_end_s for start in c.sweep_push_start_s):
        raise top.error("explain.push_start_s", f"must all lie before disturbance.end_s "
                        f"({c.push_end_s:g} s)")
    if c.limit_ma not in c.sweep_current_ma:
        raise top.error("explain.current_mA", f"must hold drive.current_limit_mA "
                        f"({c.limit_ma:g}), the paper's case the sweep starts from")


def _integers(table: Table, name: str, at_most: int | None = None) -> tuple[int, ...]:
    values = table.array(name, rule="positive integers")
    if not values or not all(isinstance(v, int) and not isinstance(v, bool) and v >= 1
                             and (at_most is None or v <= at_most) for v in values):
        bound = f" up to {at_most}" if at_most is not None else ""
        raise table.error(name, f"must be a non-empty array of positive integers{bound}, "
                          f"got {values!r}")
    return tuple(sorted(set(values)))


def _numbers(table: Table, name: str, at_least: float | None = None,
             at_most: float | None = None) -> tuple[float, ...]:
    values = table.array(name, rule="numbers")
    low = 0.0 if at_least is None else at_least

    def fits(v: object) -> bool:
        return isinstance(v, int | float) and not isinstance(v, bool) and (
            v >= low if at_least is not None else v > 0) and (at_most is None or v <= at_most)

    if not values or not all(fits(v) for v in values):
        rule = f"in [{low:g}, {at_most:g}]" if at_most is not None else (
            f">= {low:g}" if at_least is not None else "> 0")
        raise table.error(name, f"must be a non-empty array of numbers {rule}, got {values!r}")
    return tuple(float(v) for v in values)
