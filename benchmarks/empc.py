"""Explicit MPC benchmark: build time, evaluation time, and ppopt as a cross-check.

1. Build (mpQP + search tree) for FOH, H_p = 50, |u| <= 1000 mA, H_t = H_u = 3 (the paper's
   EMPC of Figs. 14/16) and 4, default box (controllers/servo/empc.py). Paper: 25 regions,
   11 controllers, 127 nodes, depth 7 for H_t = H_u = 3.
2. Evaluation of Δu(0|k) from θ for H_t = H_u = 3, per call, on θ from a closed-loop run of
   the online MPC (2 deg, 10 Hz sine at 1000 mA: saturated, several controllers) and θ
   uniform in the box: Python tree descent (the controller's hot path: relative parameters,
   descent, law), Python sequential search over the regions, the exported C through ctypes
   (per call, ctypes overhead included) and timed inside C (clock_gettime around each call,
   ~20-30 ns of it is the clock itself), next to the online QP (DaqpSolver: unconstrained
   fast path, else daqp) on the same θ in the same run. Targets (the project's): <= 10 us Python,
   <= 1 us C.
3. ppopt (if installed, benchmarks/optional-requirements.txt): region count and build time of its
   combinatorial mpQP algorithm on the same problem, and its optimiser against ours.

The machine is shared: figures are noisy, run it alone when the numbers matter. ``--quick``:
H_t = H_u = 3 only, 200 θ of each kind timed once, ppopt skipped (seconds; figures not worth
quoting).
"""

from __future__ import annotations

import argparse
import ctypes
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import add_quick

from hil.controllers.servo.empc import ExplicitSolver, build_explicit_law, relative_map
from hil.controllers.servo.empc_export import write_c
from hil.controllers.servo.empc_tree import Polyhedron, SequentialSearch
from hil.controllers.servo.mpc import DaqpSolver, MpcConfig, TrajectoryMpc
from hil.controllers.servo.references import Sine
from hil.controllers.servo.sim import simulate

PY_TARGET_US = 10.0
C_TARGET_US = 1.0
HARNESS = r"""
#define _POSIX_C_SOURCE 199309L
#include <time.h>
int empc_eval(const double theta[], double *du);
double empc_time_each(const double *thetas, int n, int n_theta, double *ns)
{
    struct timespec a, b;
    double du = 0.0, sink = 0.0;
    int i;
    for (i = 0; i < n; ++i) {
        clock_gettime(CLOCK_MONOTONIC, &a);
        empc_eval(thetas + (long)i * n_theta, &du);
        clock_gettime(CLOCK_MONOTONIC, &b);
        ns[i] = (double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec);
        sink += du;
    }
    return sink;
}
"""


def config(h: int) -> MpcConfig:
    return MpcConfig(ht=h, hu=h, hp=50, ert="foh", u_min=-1000.0, u_max=1000.0)


def build(horizons: tuple[int, ...] = (3, 4)) -> object:
    print("1. build: mpQP (combinatorial, pruned) + binary search tree, default box")
    print(f"   {'H_t=H_u':>7}{'regions':>9}{'ctrls':>7}{'nodes':>7}{'leaves':>8}{'depth':>7}"
          f"{'planes':>8}{'mpQP s':>9}{'tree s':>8}{'total s':>9}")
    law3 = None
    for h in horizons:
        law = build_explicit_law(config(h))
        s = law.summary()
        print(f"   {h:>7}{s['regions']:>9}{s['controllers']:>7}{s['tree_nodes']:>7}"
              f"{s['tree_leaves']:>8}{s['tree_depth']:>7}{s['hyperplanes']:>8}"
              f"{s['mpqp_s']:>9.2f}{s['tree_s']:>8.2f}{s['build_s']:>9.2f}")
        law3 = law3 or law
    print("   paper (H_t = H_u = 3): 25 regions, 11 controllers, 127 nodes, depth 7")
    return law3


def sample_thetas(law, rng: np.random.Generator, count: int = 2000, seconds: float = 1.0
                  ) -> tuple[np.ndarray, np.ndarray]:
    """θ seen by the online MPC in a saturated closed loop (``seconds`` of it, at most
    ``count``), and ``count`` θ uniform in the box."""
    cfg = law.config
    seen: list[np.ndarray] = []

    class Recording(TrajectoryMpc):
        def step(self, position_deg: float, t_s: float) -> float:
            seen.append(self._theta.copy())  # θ of the previous tick, fine for timing
            return super().step(position_deg, t_s)

    reference = Sine(2.0, 10.0)
    simulate(Recording(reference, cfg), reference, seconds, current_limit_ma=cfg.u_max)
    closed_loop = np.array(seen[10:count + 10])
    _, S = relative_map(law.qp, cfg.ht)
    phi = law.box.lower + (law.box.upper - law.box.lower) * rng.random((count, law.P.shape[0]))
    uniform = phi @ S.T
    y = rng.uniform(-720.0, 720.0, len(uniform))
    uniform[:, law.qp.n_x - 1] += y
    uniform[:, law.qp.n_x + 1:] += y[:, None]
    return closed_loop, uniform


def per_call_us(fn, thetas: np.ndarray, repeat: int = 3) -> np.ndarray:
    clock = time.perf_counter_ns
    out = np.empty(len(thetas) * repeat)
    k = 0
    for _ in range(repeat):
        for theta in thetas:
            t0 = clock()
            fn(theta)
            out[k] = clock() - t0
            k += 1
    return out / 1e3


def compile_c(law, folder: Path):
    source = write_c(law, folder / "empc_law.c")
    harness = folder / "harness.c"
    harness.write_text(HARNESS)
    lib = folder / "empc_law.so"
    subprocess.run(["cc", "-std=c99", "-O2", "-fPIC", "-shared", str(source), str(harness),
                    "-o", str(lib)], check=True)
    dll = ctypes.CDLL(str(lib))
    dll.empc_eval.restype = ctypes.c_int
    dll.empc_eval.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_double)]
    dll.empc_time_each.restype = ctypes.c_double
    dll.empc_time_each.argtypes = [ctypes.POINTER(ctypes.c_double), ctypes.c_int, ctypes.c_int,
                                   ctypes.POINTER(ctypes.c_double)]
    return dll


def evaluation(law, quick: bool = False) -> tuple[float, float]:
    """Print the evaluation table; return the worst p99 of the Python tree and of C [us]."""
    rng = np.random.default_rng(0)
    online = DaqpSolver(law.qp)
    explicit = ExplicitSolver(law, DaqpSolver(law.qp))
    regions = [Polyhedron(r.A, r.b, r.boundary) for r in law.solution.regions]
    sequential = SequentialSearch(regions, law.labels, law.box.lower, law.box.upper)
    P, gains, offsets = law.P, law.gains, law.offsets

    def sequential_law(theta: np.ndarray) -> float:
        phi = P @ theta
        c = sequential(phi)
        return float(gains[c] @ phi + offsets[c])

    worst_py = worst_c = 0.0
    print("\n2. evaluation of du(0|k), H_t = H_u = 3, microseconds per call "
          "(p50 / p99 / max)")
    with tempfile.TemporaryDirectory() as tmp:
        dll = compile_c(law, Path(tmp))
        du = ctypes.c_double()

        def c_call(theta: np.ndarray) -> None:
            dll.empc_eval(theta.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                          ctypes.byref(du))

        for name, thetas in zip(("closed loop, saturated sine", "uniform in the box"),
                                sample_thetas(law, rng, *((200, 0.2) if quick else ())),
                                strict=True):
            thetas = np.ascontiguousarray(thetas)
            for theta in thetas[:200]:  # the explicit law is the online QP's optimum
                assert abs(explicit.solve(theta)[0] - online.solve(theta)[0]) < 1e-6
            used = {law.evaluator(P @ t) for t in thetas}
            paths = []
            for theta in thetas:
                online.solve(theta)
                paths.append(online.last_path)
            qp_share = paths.count("qp") / len(paths)
            ns = np.empty(len(thetas))
            flat = thetas.ravel()
            for _ in range(3):  # warm caches, keep the last
                dll.empc_time_each(flat.ctypes.data_as(ctypes.POINTER(ctypes.c_double)),
                                   len(thetas), thetas.shape[1],
                                   ns.ctypes.data_as(ctypes.POINTER(ctypes.c_double)))
            repeat = 1 if quick else 3
            rows = {
                "online QP (daqp)": per_call_us(online.solve, thetas, repeat),
                "Python tree descent": per_call_us(explicit.solve, thetas, repeat),
                "Python sequential": per_call_us(sequential_law, thetas, repeat),
                "C via ctypes": per_call_us(c_call, thetas, repeat),
                "C, timed in C": ns / 1e3,
            }
            print(f"   {name}: {len(thetas)} θ, {len(used)} controllers used, "
                  f"online QP solved by daqp on {qp_share:.0%}")
            base = np.median(rows["online QP (daqp)"])
            for label, us in rows.items():
                p50, p99 = np.percentile(us, [50, 99])
                print(f"     {label:<22}{p50:>8.2f}{p99:>8.2f}{us.max():>9.1f}"
                      f"   {base / p50:>6.1f}x vs online")
            worst_py = max(worst_py, float(np.percentile(rows["Python tree descent"], 99)))
            worst_c = max(worst_c, float(np.percentile(rows["C, timed in C"], 99)))
    return worst_py, worst_c


def ppopt_comparison(law) -> None:
    print("\n3. ppopt on the same mpQP (normalised relative parameters, H_t = H_u = 3)")
    try:
        from ppopt.mp_solvers.solve_mpqp import mpqp_algorithm, solve_mpqp
        from ppopt.mpqp_program import MPQP_Program
    except ImportError:
        print("   ppopt not installed (benchmarks/optional-requirements.txt): skipped")
        return
    problem = law.solution.problem.normalised()
    n = problem.n_params
    start = time.perf_counter()
    program = MPQP_Program(problem.G, problem.W[:, None], problem.f[:, None], problem.F.T,
                           problem.H, np.vstack([np.eye(n), -np.eye(n)]), np.ones((2 * n, 1)),
                           problem.X)
    solution = solve_mpqp(program, mpqp_algorithm.combinatorial)
    elapsed = time.perf_counter() - start
    rng = np.random.default_rng(1)
    d, c = law.solution.problem.half_width, law.solution.problem.centre
    gaps = []
    for t in rng.uniform(-1.0, 1.0, (500, n)):
        theirs = solution.evaluate(t[:, None])
        ours = law.solution.optimiser(c + d * t)
        if theirs is not None and ours is not None:
            gaps.append(np.abs(np.ravel(theirs) - ours).max())
    print(f"   ppopt: {len(solution.critical_regions)} regions in {elapsed:.2f} s; hil: "
          f"{len(law.solution.regions)} regions in {law.solution.build_s:.2f} s (mpQP only)")
    print(f"   optimiser gap on {len(gaps)} of 500 random parameters: "
          f"max {max(gaps, default=float('nan')):.1e} mA")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    add_quick(parser)
    args = parser.parse_args()
    law = build((3,) if args.quick else (3, 4))
    worst_py, worst_c = evaluation(law, args.quick)
    if args.quick:
        print("\n3. ppopt: skipped (--quick)")
    else:
        ppopt_comparison(law)
    print(f"\ntargets: Python tree p99 {worst_py:.2f} us (<= {PY_TARGET_US:g}): "
          f"{'ok' if worst_py <= PY_TARGET_US else 'MISSED'}; C p99 {worst_c:.3f} us "
          f"(<= {C_TARGET_US:g}): {'ok' if worst_c <= C_TARGET_US else 'MISSED'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
