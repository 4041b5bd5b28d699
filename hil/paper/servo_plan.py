"""The sessions of the servo paper's reproduction, planned from its conditions: every run by
the key the tables find it under (:func:`plan`), and the PID whose feed-forward matches
Fig. 6, run once the sweep has found it (:func:`matched_pid`).
"""

from __future__ import annotations

from typing import Any

from hil.paper.servo_conditions import ServoConditions, SineCase
from hil.paper.servo_explain import vff_match
from hil.paper.servo_runs import Run, Session, SessionRunner, mpc_params, recorded_empc


def sine_run(c: ServoConditions, case: SineCase, controller: str, ert: str = "foh",
             ht: int = 8, params: dict[str, float] | None = None) -> Run:
    """One run on a sine case: ``controller`` "mpc" (``ert``, ``ht``) or "pid", ``params``
    laid over the paper's (Q, R; Table I)."""
    changed = params or {}
    if controller == "mpc":
        label = f"mpc-{ert}-ht{ht}"
        what = f"{case.title}, MPC {ert.upper()} H_t = {ht}"
        given = mpc_params(c, **changed)
    else:
        label, what, given = "pid", f"{case.title}, PID", {**c.pid_params, **changed}
    extra = "".join(f"-{key}{value:g}" for key, value in sorted(changed.items()))
    what += "".join(f", {key} = {value:g}" for key, value in sorted(changed.items()))
    return Run(name=f"sine-{case.name}-{label}{extra}", what=what, controller=controller,
               reference=c.sine_spec(case.frequency_hz),
               duration_s=c.sine_duration_s(case.frequency_hz), limit_ma=case.limit_ma,
               settle_s=c.settle_s, ert=ert, ht=ht, params=given)


def plan(c: ServoConditions, law: Any) -> dict[str, Run]:
    """Every session, by the key the tables find it under."""
    runs: dict[str, Run] = {}
    for case in c.sine_cases:
        for ht in c.horizons:
            runs[f"{case.name}/zoh/{ht}"] = sine_run(c, case, "mpc", "zoh", ht)
            if ht >= 2:
                runs[f"{case.name}/foh/{ht}"] = sine_run(c, case, "mpc", "foh", ht)
        runs[f"{case.name}/pid"] = sine_run(c, case, "pid")
    fast = c.fast
    for limit in c.sweep_current_ma:
        runs[f"current/{limit:g}"] = sine_run(c, SineCase(fast.frequency_hz, limit), "mpc",
                                              "foh", c.fig5_ht)
    for r in c.sweep_r:
        runs[f"r/{r:g}"] = sine_run(c, fast, "mpc", "foh", c.fig5_ht,
                                    None if r == c.r else {"r": r})
    for vff in c.sweep_vff:
        runs[f"vff/{vff:g}"] = sine_run(c, fast, "pid", params={"vff": vff} if vff else None)
    empc = recorded_empc(law)
    h = c.empc_ht
    for key, reference, duration in (
            ("trapezoid", c.trapezoid_spec, c.trapezoid_duration_s),
            ("disturbance", c.disturbance_spec, c.disturbance_duration_s)):
        for kind, name, controller in (("empc", "explicit", empc), ("mpc", "online", "mpc")):
            runs[f"{key}/{kind}"] = Run(
                name=f"{key}-{kind}-ht{h}", what=f"{key}, {name} MPC H_t = {h}",
                controller=controller, reference=reference, duration_s=duration,
                limit_ma=c.limit_ma, ht=h, params=mpc_params(c))
    for start in c.sweep_push_start_s:
        runs[f"push/{start:g}"] = runs["disturbance/empc"] if start == c.push_start_s else Run(
            name=f"disturbance-empc-ht{h}-start{start:g}", controller=empc,
            what=f"disturbance from {start:g} s, explicit MPC H_t = {h}",
            reference=c.push_spec(start), duration_s=c.disturbance_duration_s,
            limit_ma=c.limit_ma, ht=h, params=mpc_params(c))
    runs["trapezoid/pid"] = Run(name="trapezoid-pid", what="trapezoid, PID", controller="pid",
                                reference=c.trapezoid_spec, duration_s=c.trapezoid_duration_s,
                                limit_ma=c.limit_ma, params=c.pid_params)
    return runs


def matched_pid(c: ServoConditions, done: dict[str, Session],
                run: SessionRunner) -> dict[str, Session]:
    """The PID whose feed-forward share matches Fig. 6 (:func:`vff_match`) on every sine (the
    fast one at the rated current), run once the sweep has found the share."""
    share = vff_match(c, done)
    if share is None:
        return {}
    run.planned += len(c.frequencies_hz)
    cases = {f: c.fast if f == c.fast.frequency_hz else SineCase(f, c.limit_ma)
             for f in c.frequencies_hz}
    return {f"matched/{f:g}": run(sine_run(c, case, "pid", params={"vff": share}))
            for f, case in cases.items()}
