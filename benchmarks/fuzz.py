"""The fuzz campaign, longer: every target of tests/fuzz (each byte parser hil owns, through
the real wire where that is cheap) for ``--seconds`` each, new random cases every round
(``make test`` runs a fixed few), findings shrunk to their smallest input.

Prints, per target: the cases drawn, the seconds spent, cases per second, and the finding if
any (the rule it broke and the smallest input that breaks it, with the seed that draws it
again: ``--only TARGET --seed N``). Exit status 1 when anything was found. The machine is
shared: cases per second are noisy. ``--quick``: 2 cases per target, the same every run
(seconds in all; the same kinds of figures, not worth quoting).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from benchkit import add_quick, fill_defaults
from hypothesis import HealthCheck, Phase, settings

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.fuzz.harness import LIMITS, Target, run_target
from tests.fuzz.targets import TARGETS

ROUND_S = 2.0  # a round of cases drawn in one go, about this long (the rig opened once each)
QUICK_CASES = 2  # --quick: this many cases per target, from the same seed every run


@dataclass
class Tally:
    target: str
    cases: int = 0
    seconds: float = 0.0
    finding: str = ""


def fuzz(target: Target, seconds: float, first_seed: int, shrink: bool,
         fixed_round: int | None = None) -> Tally:
    """``target``'s cases for ``seconds``, round after round, each from a new seed; or one
    round of ``fixed_round`` cases (the same ones every run)."""
    tally = Tally(target.name)
    started = time.monotonic()
    per_round, seed = fixed_round or 5, first_seed

    def count() -> None:
        tally.cases += 1

    phases = (Phase.generate, Phase.shrink) if shrink else (Phase.generate,)
    while time.monotonic() - started < seconds:
        round_started, before = time.monotonic(), tally.cases
        run_settings = settings(max_examples=per_round, deadline=None, database=None,
                                suppress_health_check=list(HealthCheck), phases=phases,
                                print_blob=False)
        try:
            run_target(target, run_settings, count, seed=seed)
        except Exception as exc:
            notes = "\n".join(getattr(exc, "__notes__", []))
            first = next(iter(str(exc).splitlines()), "")
            tally.finding = f"seed {seed}: {type(exc).__name__}: {first}\n{notes}"
            break
        if fixed_round:
            break
        took = time.monotonic() - round_started
        drawn = max(1, tally.cases - before)
        per_round = max(1, min(5000, round(drawn * ROUND_S / max(took, 1e-3))))
        seed += 1
    tally.seconds = time.monotonic() - started
    return tally


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float,
                        help="per target (default 60; with --quick: one round of "
                        f"{QUICK_CASES} cases, the same every run)")
    parser.add_argument("--only", action="append", metavar="TARGET",
                        help="this target only (repeatable); names: "
                        + ", ".join(t.name for t in TARGETS))
    parser.add_argument("--seed", type=int, default=0, help="the first round's seed")
    parser.add_argument("--hang-s", type=float, default=LIMITS.hang_s,
                        help=f"a case longer than this is a hang (default {LIMITS.hang_s:g})")
    parser.add_argument("--no-shrink", action="store_true",
                        help="report a finding as drawn (shrinking a hang costs its bound "
                        "per try)")
    add_quick(parser)
    args = parser.parse_args()
    fixed_round = QUICK_CASES if args.quick and args.seconds is None else None
    fill_defaults(args, {"seconds": (60.0, 60.0)})
    LIMITS.hang_s = args.hang_s
    unknown = set(args.only or ()) - {t.name for t in TARGETS}
    if unknown:
        parser.error(f"unknown target(s) {', '.join(sorted(unknown))}")
    chosen = [t for t in TARGETS if not args.only or t.name in args.only]
    print(f"{'target':<24} {'cases':>8} {'seconds':>8} {'cases/s':>9}  finding")
    tallies = []
    for target in chosen:
        tally = fuzz(target, args.seconds, args.seed, shrink=not args.no_shrink,
                     fixed_round=fixed_round)
        tallies.append(tally)
        rate = tally.cases / tally.seconds if tally.seconds else 0.0
        print(f"{tally.target:<24} {tally.cases:>8} {tally.seconds:>8.1f} {rate:>9.1f}  "
              f"{tally.finding.splitlines()[0] if tally.finding else '-'}", flush=True)
    found = [t for t in tallies if t.finding]
    total = sum(t.cases for t in tallies)
    print(f"\n{total} cases in {sum(t.seconds for t in tallies):.1f} s over {len(tallies)} "
          f"targets; {len(found)} finding(s)")
    for tally in found:
        print(f"\n== {tally.target}\n{tally.finding}")
    sys.exit(1 if found else 0)


if __name__ == "__main__":
    main()
