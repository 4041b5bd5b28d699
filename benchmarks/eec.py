"""EEC solve time per decision, next to the naive baseline, and the relay
wear trade-off of gamma3.

Closed-loop lockstep runs of the EEC against the emulated bench over Modbus TCP, default
config (solver ``dp``, budget ``time_limit_s`` of hil/configs/eec.toml), every decision's
instance kept; and of the hysteresis baseline (BC) under the same conditions. Printed:

1. the target table: H_p = T (28 s), ``--cycles`` machine cycles, nominal and with the
   emulator's disturbance: solve median, p99, max, solves stopped at the budget, J2 and J2
   against BC; H_p = 2T with ``--cycles-2t`` cycles: median, p99, at the budget;
2. the same instances re-solved by each method with no budget to speak of (20 s): the
   schedule DP, the HiGHS MILP (every ``--exact-every``-th instance) and the naive cvxpy
   formulation rebuilt for every decision (:func:`hil.controllers.bench.eec_cvxpy.solve_naive`, the
   baseline; ``--naive`` instances, ``--naive-limit`` seconds each), with how many
   objectives agree with the DP's;
3. the gamma3 trade-off: runs of ``--sweep-cycles`` cycles for a few costs per switch-on:
   energy per cycle (J1 / cycles), peak J2, starts per hour of each peripheral.

Targets: H_p = T median <= 20 ms, p99 <= 100 ms, none at the budget, J2 the same as the
exact MILP; H_p = 2T median <= 100 ms, none at the budget. The machine is shared: figures
are noisy, run it on a quiet box for figures worth quoting. ``--quick``: one machine cycle
per run, H_p = T and the nominal case only, no naive baseline, gamma3 = 0 only (seconds instead
of 6-7 minutes; figures not worth quoting). The former middle size
(about 3 minutes) is ``--cycles 3 --cycles-2t 2 --sweep-cycles 1 --naive 1``.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from typing import Any
from unittest import mock

import numpy as np
from benchkit import add_quick

from hil.bench.kpis import timing_summary
from hil.bench.run import BenchRunOptions, run_bench
from hil.controllers.bench.eec_solver import HorizonSolver

DP, MILP, NAIVE = ("DP (schedule DP, default)", "MILP (HiGHS)",
                   "naive cvxpy, rebuilt per decision")
Inputs = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]
QUICK_RUN_S = 14.0  # --quick's runs: half a machine cycle of session time

@dataclasses.dataclass
class Run:
    kpis: dict[str, Any]
    inputs: list[Inputs]          # every solve's instance
    solve_ms: list[float]
    solver: HorizonSolver | None
    wall_s: float


def closed_loop(controller: str, cycles: int, hp_s: int | None = None,
                disturbance: bool = False, overrides: dict[str, Any] | None = None,
                duration_s: float | None = None) -> Run:
    """One run of ``cycles`` machine cycles (``duration_s``: that long instead); for the EEC
    every solve's inputs and time are kept."""
    inputs: list[Inputs] = []
    solve_ms: list[float] = []
    solvers: list[HorizonSolver] = []
    original = HorizonSolver.solve

    def recording(self, free, u_prev, fixed, q0, t_s, warm_u=None, budget_s=None):
        result = original(self, free, u_prev, fixed, q0, t_s, warm_u, budget_s)
        inputs.append((free.copy(), u_prev.copy(), fixed.copy(), q0.copy(), t_s))
        solve_ms.append(result.solve_ms)
        solvers.append(self)
        return result

    t0 = time.perf_counter()
    with mock.patch.object(HorizonSolver, "solve", recording), \
            tempfile.TemporaryDirectory() as tmp:
        kpis = run_bench(BenchRunOptions(controller=controller, cycles=cycles, hp_s=hp_s,
                                         disturbance=disturbance, out=f"{tmp}/run.mcap",
                                         overrides=overrides or {},
                                         duration_s=duration_s)).kpis
    return Run(kpis, inputs, solve_ms, solvers[0] if solvers else None,
               time.perf_counter() - t0)


def fmt(summary: dict) -> str:
    return f"{summary['median']:>8.1f} {summary['p99']:>8.1f} {summary['max']:>8.1f}"


def exact_table(label: str, run: Run, every: int, naive: int, naive_limit_s: float
                ) -> dict[str, float]:
    """Re-solve the run's instances by each method without a budget; print and return the
    medians."""
    assert run.solver is not None
    base = run.solver.horizon
    solvers = {s: HorizonSolver(base.p, base.problem, dataclasses.replace(
        base.settings, time_limit_s=20.0, solver=s)) for s in ("dp", "milp")}
    dp = [solvers["dp"].solve(*x) for x in run.inputs]
    sample = list(range(0, len(run.inputs), every))
    milp = [solvers["milp"].solve(*run.inputs[k]) for k in sample]
    picks = [int(k) for k in np.linspace(0, len(run.inputs) - 1, naive).round()] if naive \
        else []
    cvx = []
    if picks:  # cvxpy takes 1-2 s to import: only for the naive baseline (not with --quick)
        from hil.controllers.bench.eec_cvxpy import solve_naive
        cvx = [solve_naive(base, *run.inputs[k], time_limit_s=naive_limit_s)  # type: ignore[misc]
               for k in picks]
    # the fast model's step peaks may overestimate by peak_overestimate_va (model tails)
    slack = (base.w2 + base.w_limit) * base.peak_overestimate_va
    medians = {}
    rows: list[tuple[str, list[Any], Any]] = [(DP, dp, range(len(dp))), (MILP, milp, sample),
                                             (NAIVE, cvx, picks)]
    for name, results, idx in rows:
        if not results:
            continue
        ms = [r.solve_ms for r in results]
        agree = sum(abs(r.objective - dp[k].objective) <= 1e-6 * abs(dp[k].objective) + (
            slack if results is cvx else 0.0) for r, k in zip(results, idx, strict=True))
        unproven = sum(r.status != "optimal" for r in results)
        limit = naive_limit_s if results is cvx else 20.0
        s = timing_summary(ms)
        medians[name] = s["median"]
        print(f"  {label:<10} {name:<36} {len(ms):>4} {fmt(s)}  objective = DP's on "
              f"{agree}/{len(ms)}" + (f"; {unproven} stopped at its {limit:g} s limit"
                                      if unproven else ""))
    return medians


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_quick(parser)
    parser.add_argument("--cycles", type=int, help="machine cycles at H_p = T (default 8)")
    parser.add_argument("--cycles-2t", type=int,
                        help="machine cycles at H_p = 2T (default 3; not run with --quick)")
    parser.add_argument("--sweep-cycles", type=int, help="cycles per gamma3 run (default 3)")
    parser.add_argument("--exact-every", type=int,
                        help="re-solve every Nth instance by the MILP (default 8; 28 with "
                             "--quick)")
    parser.add_argument("--naive", type=int, help="instances per horizon for the naive "
                        "cvxpy baseline (default 2)")
    parser.add_argument("--naive-limit", type=float, default=60.0,
                        help="time limit of a naive cvxpy solve [s]")
    parser.add_argument("--gamma3", type=float, nargs="+",
                        help="costs per switch-on of the trade-off table (default 0 0.02 0.1 1; "
                             "1 with --quick)")
    args = parser.parse_args()
    cycles = args.cycles or (1 if args.quick else 8)
    cycles_2t = args.cycles_2t or (1 if args.quick else 3)
    sweep_cycles = args.sweep_cycles or (1 if args.quick else 3)
    naive = args.naive if args.naive is not None else (0 if args.quick else 2)
    gammas = args.gamma3 or ([0.0] if args.quick else [0.0, 0.02, 0.1, 1.0])
    exact_every = args.exact_every or (28 if args.quick else 8)
    cases = (("nominal", False),) if args.quick else (("nominal", False), ("disturbed", True))
    # --quick: every run half a machine cycle of session time, enough for the solves of every
    # path (the trade-off table's runs too, so its rows and BC's are alike)
    duration_s = QUICK_RUN_S if args.quick else None
    length = f"{QUICK_RUN_S:g} s" if args.quick else f"{cycles} cyc"
    t_start = time.perf_counter()

    runs: dict[Any, Run] = {}
    for case, disturbed in cases:
        runs[case, "bc"] = closed_loop("bc", cycles, disturbance=disturbed,
                                       duration_s=duration_s)
        runs[case, "eec"] = closed_loop("eec", cycles, hp_s=28, disturbance=disturbed,
                                        duration_s=duration_s)
    if not args.quick:
        runs["2T"] = closed_loop("eec", cycles_2t, hp_s=56)
    eec_run = runs["nominal", "eec"]
    assert eec_run.solver is not None
    settings = eec_run.solver.horizon.settings
    budget_ms = settings.time_limit_s * 1e3

    print(f"1. Targets (closed loop, default config: solver "
          f"{settings.solver.upper()}, budget {budget_ms:g} ms)")
    print(f"  {'case':<24} {'n':>4} {'median':>8} {'p99':>8} {'max':>8}  at limit  "
          f"{'J2 [VA]':>8}  {'J2 BC':>8}  J2 vs BC   targets")
    for case, _ in cases:
        run, bc = runs[case, "eec"], runs[case, "bc"]
        j2, j2_bc = run.kpis["J2_VA"], bc.kpis["J2_VA"]
        print(f"  {f'H_p = T, {case}, {length}':<24} {len(run.solve_ms):>4} "
              f"{fmt(timing_summary(run.solve_ms))}  {run.kpis['solves_at_limit']:>8}  "
              f"{j2:>8.1f}  {j2_bc:>8.1f}  {100 * (j2 / j2_bc - 1):>+7.1f} %   "
              "median <= 20, p99 <= 100, 0 at limit")
    if args.quick:
        print("  (the disturbed case and H_p = 2T: skipped, --quick)")
    else:
        run = runs["2T"]
        print(f"  {f'H_p = 2T, {cycles_2t} cyc':<24} {len(run.solve_ms):>4} "
              f"{fmt(timing_summary(run.solve_ms))}  {run.kpis['solves_at_limit']:>8}  "
              f"{run.kpis['J2_VA']:>8.1f}  {'':>8}  {'':>9}   median <= 100, 0 at limit")
    print("  (ms; max_gap " + ", ".join(
        f"{k if isinstance(k, str) else '/'.join(k)} {r.kpis['max_gap']:.3g}"
        for k, r in runs.items() if r.solver is not None) + ")")

    print("\n2. The same instances, each method without a budget (20 s): ms median, p99, max")
    print(f"  {'H_p':<10} {'method':<36} {'n':>4} {'median':>8} {'p99':>8} {'max':>8}")
    speedups = []
    horizons: tuple[tuple[str, Any], ...] = (("T", ("nominal", "eec")), ("2T", "2T"))
    if args.quick:
        print("  (H_p = 2T and the naive cvxpy baseline: skipped, --quick)")
        horizons = horizons[:1]
    for label, key in horizons:
        medians = exact_table(label, runs[key], exact_every, naive, args.naive_limit)
        naive_ms = medians.get(NAIVE)
        if naive_ms:
            speedups.append(f"H_p = {label}: DP {naive_ms / medians[DP]:.0f}x, "
                            f"MILP {naive_ms / medians[MILP]:.0f}x")
    if speedups:
        print("  median speed-up over the naive baseline: " + "; ".join(speedups))

    # the runs of section 1 are as long as this table's (--quick: all of one length)
    same_length = args.quick or sweep_cycles == cycles
    print(f"\n3. Relay wear: gamma3 (cost per switch-on, units of J), H_p = T, nominal, "
          f"{length if args.quick else f'{sweep_cycles} cycles'}")
    print(f"  {'gamma3':>8} {'J1/cycle [VA s]':>16} {'J2 [VA]':>8} {'starts/h P1':>12} "
          f"{'starts/h P2':>12} {'solve median ms':>16}")
    # BC takes no gamma3: the nominal run of section 1 is the same run when the lengths agree
    bc = runs["nominal", "bc"] if same_length else closed_loop("bc", sweep_cycles)
    for gamma3 in gammas:
        # the nominal run of section 1 is this one when its gamma3 and length agree
        nominal = same_length and eec_run.solver is not None \
            and eec_run.solver.horizon.settings.gamma3 == gamma3
        run = eec_run if nominal else closed_loop("eec", sweep_cycles, hp_s=28,
                                                  overrides={"gamma3": gamma3},
                                                  duration_s=duration_s)
        k = run.kpis
        print(f"  {gamma3:>8g} {k['SEC_VA']:>16.1f} {k['J2_VA']:>8.1f} "
              f"{k['starts_per_hour']['P1']:>12.1f} {k['starts_per_hour']['P2']:>12.1f} "
              f"{timing_summary(run.solve_ms)['median']:>16.1f}")
    k = bc.kpis
    print(f"  {'BC':>8} {k['SEC_VA']:>16.1f} {k['J2_VA']:>8.1f} "
          f"{k['starts_per_hour']['P1']:>12.1f} {k['starts_per_hour']['P2']:>12.1f}")
    print(f"\ntotal {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
