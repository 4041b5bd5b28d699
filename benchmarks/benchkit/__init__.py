"""What every benchmark script shares: its ``--quick`` flag (a seconds-long run that checks the
script still works; ``make test`` runs every benchmark this way) and the defaults that flag
picks; and the code before a change (``--baseline-code``, or git's) to measure against in the
same run."""

from __future__ import annotations

import argparse
import subprocess
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

#: the repository the benchmarks belong to
REPO = Path(__file__).resolve().parents[2]

QUICK_HELP = ("a seconds-long run that checks the benchmark still works: fewer repeats, shorter "
              "runs, smaller sizes, optional baselines skipped; the same kind of figures, not "
              "worth quoting (tests/test_benchmarks.py runs every benchmark this way)")


def add_quick(parser: argparse.ArgumentParser) -> None:
    """The ``--quick`` flag."""
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)


def fill_defaults(args: argparse.Namespace, defaults: Mapping[str, tuple[Any, Any]]) -> None:
    """Every option of ``defaults`` (name -> (full run's value, --quick's)) that the command
    line left out."""
    for name, (full, quick) in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, quick if args.quick else full)


def git(*args: str) -> str:
    """``git ARGS`` in the repository, its output stripped (CalledProcessError on failure)."""
    return subprocess.run(["git", "-C", str(REPO), *args], capture_output=True, text=True,
                          check=True).stdout.strip()


def extract_code(ref: str, folder: Path) -> str | None:
    """hil's code (hil, drivers, emulators, controllers) at ``ref`` extracted into ``folder``
    with ``git archive``, a baseline to measure against; None, or why not."""
    archive = subprocess.Popen(["git", "-C", str(REPO), "archive", ref, "hil", "drivers",
                                "emulators", "controllers"], stdout=subprocess.PIPE)
    subprocess.run(["tar", "-x", "-C", str(folder)], stdin=archive.stdout, check=True)
    return None if archive.wait() == 0 else f"git archive {ref} failed"


def code_before(commit: str, folder: Path) -> tuple[Path | None, str]:
    """hil's code at the parent of ``commit`` extracted into ``folder``: (``folder``, the
    parent's short hash), or (None, why not)."""
    try:
        ref = git("rev-parse", "--short", f"{commit}^")
        failed = extract_code(ref, folder)
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"not a git checkout with its history ({exc})"
    return (None, failed) if failed else (folder, ref)


def code_before_adding(path: str, folder: Path) -> tuple[Path | None, str]:
    """hil's code at the parent of the commit that added ``path`` (a file of the
    repository), extracted into ``folder``: (``folder``, that commit), or (None, why not)."""
    try:
        added = git("log", "--diff-filter=A", "--format=%H", "HEAD", "--", path)
    except (OSError, subprocess.CalledProcessError) as exc:
        return None, f"not a git checkout with its history ({exc})"
    if not added:
        return None, f"no commit adds {path} in this checkout's history"
    return code_before(added.splitlines()[-1], folder)


def add_baseline_code(parser: argparse.ArgumentParser, default: str) -> None:
    """``--baseline-code DIR``: the code to measure against instead of ``default`` (what the
    script extracts with git)."""
    parser.add_argument("--baseline-code", type=Path, metavar="DIR",
                        help=f"the code before: this checkout (default: git archive of "
                        f"{default})")


def baseline_code(given: Path | None, folder: Path,
                  default: Callable[[Path], tuple[Path | None, str]]
                  ) -> tuple[Path | None, str]:
    """The code before: ``given`` (``--baseline-code``), else ``default(folder / "before")``'s
    (the folder made here); (None, why not) when there is none."""
    if given is not None:
        return given.resolve(), str(given)
    (folder / "before").mkdir()
    return default(folder / "before")
