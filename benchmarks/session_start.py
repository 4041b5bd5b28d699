"""Sessions one after another in one process: what each costs with this code (its writer forked
by the process's fork server) against the code before (a fresh writer interpreter per session:
``git archive`` of the parent of the commit that added hil/core/recording/writer_fork.py, or
``--baseline-code DIR``), alternated, in the same run.

A child process per run records ``--sessions`` short lockstep sessions (100 messages each), as
a test suite's or a script's runs follow one another. Printed for each code, medians over
``--repeats`` runs: the first session's wall time (the fork server's start, or the first
writer's), then per later session its wall time and the CPU time of the child, its writers
and its fork server (from /proc: the server is not the child's to reap), and after/before.

The first session here waits for the fork server's start, as a script's first ``Recorder``
does; a run command (``hil servo run``...) starts the server as it begins, beside its own
imports (``hil.core.recording.writer_fork.start_server``), so its first session finds it up.

Then the start-up goal: ``hil servo run --controller pid --duration 0.1`` from the command's
start to its end, with each code (alternated with the sessions' runs, one untimed run of each
first: the bytecode), against at most 0.4 s.

``--quick``: 5 sessions, one run of each code (seconds; figures not worth quoting).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchkit import (
    REPO,
    add_baseline_code,
    add_quick,
    baseline_code,
    code_before_adding,
    fill_defaults,
)

FORK_SERVER = "hil/core/recording/writer_fork.py"

#: the child: N sessions, then the first one's wall time and the later ones' wall and CPU [s]
CHILD = r"""
import os, resource, sys, time
from hil.core.recording.recorder import Recorder

def cpu_s():
    own = sum(getattr(resource.getrusage(who), field)
              for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
              for field in ("ru_utime", "ru_stime"))
    for task in os.listdir("/proc/self/task"):
        for pid in open(f"/proc/self/task/{task}/children").read().split():
            try:
                if open(f"/proc/{pid}/comm").read().strip() == "hil writer fork":
                    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
                    own += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
            except OSError:
                pass
    return own

count, folder = int(sys.argv[1]), sys.argv[2]
schema = {"type": "object", "properties": {"k": {"type": "integer"}}}
began = time.perf_counter()
marks = []
for i in range(count):
    with Recorder(os.path.join(folder, f"{i}.mcap"), wait_when_full=True) as rec:
        topic = rec.topic("/k", schema)
        for k in range(100):
            topic.log(k * 500_000, {"k": k})
    marks.append((time.perf_counter(), cpu_s()))
print(marks[0][0] - began, marks[-1][0] - marks[0][0], marks[-1][1] - marks[0][1])
"""


#: the start-up goal's run, from the command line
RUN = ["-m", "hil", "servo", "run", "--controller", "pid", "--duration", "0.1"]
STARTUP_GOAL_S = 0.4


def run_command_s(code: Path, out: Path) -> float:
    """:data:`RUN` with ``code``, recorded to ``out``: its wall time from start to end [s]."""
    begin = time.perf_counter()
    done = subprocess.run([sys.executable, *RUN, "--out", str(out)], cwd=out.parent,
                          capture_output=True, text=True, check=False,
                          env={**os.environ, "PYTHONPATH": str(code)})
    elapsed = time.perf_counter() - begin
    if done.returncode != 0:
        raise SystemExit(f"hil servo run with {code} failed:\n{done.stderr[-2000:]}")
    return elapsed


def run_child(code: Path, sessions: int, folder: Path) -> tuple[float, float, float]:
    """One child's sessions with ``code``: first session [s], then per later session its wall
    and CPU [s]."""
    done = subprocess.run([sys.executable, "-c", CHILD, str(sessions), str(folder)],
                          cwd=folder, capture_output=True, text=True, check=False,
                          env={**os.environ, "PYTHONPATH": str(code)})
    if done.returncode != 0:
        raise SystemExit(f"sessions with {code} failed:\n{done.stderr[-2000:]}")
    first, wall, cpu = map(float, done.stdout.split())
    return first, wall / (sessions - 1), cpu / (sessions - 1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sessions", type=int, help="sessions a run records (40)")
    parser.add_argument("--repeats", type=int, help="runs of each code (5)")
    add_baseline_code(parser, f"the parent of the commit that added {FORK_SERVER}")
    add_quick(parser)
    args = parser.parse_args()
    fill_defaults(args, {"sessions": (40, 5), "repeats": (5, 1)})
    if args.sessions < 2:
        parser.error(f"--sessions {args.sessions}: at least 2 (the first one is timed apart)")
    with tempfile.TemporaryDirectory(prefix="hil-bench-sessions-") as tmp:
        folder = Path(tmp)
        before, why = baseline_code(args.baseline_code, folder,
                                    lambda into: code_before_adding(FORK_SERVER, into))
        codes = {"after": REPO, **({"before": before} if before is not None else {})}
        runs: dict[str, list[tuple[float, float, float]]] = {name: [] for name in codes}
        commands: dict[str, list[float]] = {name: [] for name in codes}
        for name, code in codes.items():  # untimed: each code's first run writes its bytecode
            run_command_s(code, folder / f"warm-{name}.mcap")
        for repeat in range(args.repeats):
            for name, code in codes.items():
                out = folder / f"{name}{repeat}"
                out.mkdir()
                runs[name].append(run_child(code, args.sessions, out))
                commands[name].append(run_command_s(code, out / "run.mcap"))
        print(f"{args.sessions} lockstep sessions one after another in one process, "
              f"medians of {args.repeats} run(s)" + ("" if before else f"; no code before: {why}"))
        median = {name: [statistics.median(run[i] for run in got) for i in range(3)]
                  for name, got in runs.items()}
        for name, (first, wall, cpu) in median.items():
            label = "this code (forked writers)" if name == "after" else \
                f"the code before ({why}: a writer interpreter a session)"
            print(f"  {label}: first session {first * 1e3:.0f} ms; each later one "
                  f"{wall * 1e3:.1f} ms wall, {cpu * 1e3:.1f} ms CPU")
        if "before" in median:
            after, old = median["after"], median["before"]
            print(f"  after/before, each later session: wall {after[1] / old[1]:.2f}x, "
                  f"CPU {after[2] / old[2]:.2f}x; first session {after[0] / old[0]:.2f}x")
        startup = {name: statistics.median(got) for name, got in commands.items()}
        before_text = f", the code before {startup['before']:.3f} s (" \
            f"{startup['after'] / startup['before']:.2f}x)" if "before" in startup else ""
        print(f"hil {' '.join(RUN[2:])}, start to end, medians of {args.repeats}: this code "
              f"{startup['after']:.3f} s{before_text}")
        met = "met" if startup["after"] <= STARTUP_GOAL_S else "MISSED"
        print(f"targets\n   start-up <= {STARTUP_GOAL_S} s ({startup['after']:.3f} s): {met}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
