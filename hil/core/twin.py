"""How close a twin comes to its machine: the twin's response to a recording's commands set
against the recording's own response, output by output (fit, largest and RMS error), and the
verdict of a minimum fit. The applications make the twin's response
(:mod:`hil.servo.twin`); this module only compares and draws.

Fit is the identification's (``hil identify``): ``100 (1 - ||y - y_twin|| / ||y - mean(y)||)``
in percent, 100 for a perfect twin, 0 for one no better than the recording's mean.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from hil.core.kpi_text import fit_text
from hil.core.recording.reader import SessionData


@dataclass(frozen=True)
class OutputFit:
    """One output of the twin against the recording: fit [%], largest and RMS error [unit]."""

    name: str
    unit: str
    fit_pct: float
    max_error: float
    rms_error: float
    samples: int


@dataclass(frozen=True)
class TwinCheck:
    """Every compared output and the minimum fit each must reach."""

    outputs: tuple[OutputFit, ...]
    min_fit_pct: float

    @property
    def passed(self) -> bool:
        return all(
            math.isfinite(o.fit_pct) and o.fit_pct >= self.min_fit_pct for o in self.outputs)

    def document(self) -> dict[str, Any]:
        """The ``--json`` document: ``passed``, ``min_fit_pct`` and
        ``outputs`` (one object per output: ``name``, ``unit``, ``fit_pct``, ``max_error``,
        ``rms_error``, ``samples``)."""
        return {"passed": self.passed, "min_fit_pct": self.min_fit_pct,
                "outputs": [asdict(output) for output in self.outputs]}


def compare_output(name: str, unit: str, recorded: np.ndarray, twin: np.ndarray) -> OutputFit:
    """``twin`` against ``recorded`` over the samples both have."""
    n = min(recorded.size, twin.size)
    y, y_twin = np.asarray(recorded[:n], dtype=float), np.asarray(twin[:n], dtype=float)
    error = y - y_twin
    error_norm = float(np.linalg.norm(error))
    spread = float(np.linalg.norm(y - y.mean())) if n else 0.0
    if spread > 0:
        fit = 100.0 * (1.0 - error_norm / spread)
    else:  # a constant recording: only a twin that holds it exactly fits
        fit = 100.0 if error_norm == 0 else -math.inf
    return OutputFit(name, unit, fit, float(np.max(np.abs(error))) if n else math.nan,
                     float(np.sqrt(np.mean(error ** 2))) if n else math.nan, n)


#: an output of the twin set against the recording: its fit, the recorded and the twin's series
Compared = tuple[OutputFit, np.ndarray, np.ndarray]


def check_topic(recorded: Mapping[str, np.ndarray], units: Mapping[str, str],
                twin: SessionData, topic: str, min_fit_pct: float
                ) -> tuple[TwinCheck, list[Compared]]:
    """Each field of ``recorded`` (its unit in ``units``) against the same field of the twin's
    ``topic``: the check, and each output's fit with both series (for the plot)."""
    messages = twin.topic(topic)
    pairs = []
    for name, series in recorded.items():
        mine = np.array([m[name] for _, m in messages], dtype=float)
        pairs.append((compare_output(name, units[name], series, mine), series, mine))
    return TwinCheck(tuple(fit for fit, _, _ in pairs), min_fit_pct), pairs


def format_check(check: TwinCheck, recorded: str, twin: str) -> str:
    """The text report: a line per output, then the verdict."""
    lines = [f"twin check of {recorded} (twin's session: {twin})"]
    for o in check.outputs:
        lines.append(f"  {o.name:<16} fit {fit_text(o.fit_pct):>9}   max error "
                     f"{o.max_error:.4g} {o.unit}   RMS error {o.rms_error:.4g} {o.unit}   "
                     f"({o.samples} samples)")
    verdict = "PASS" if check.passed else "FAIL"
    lines.append(f"{verdict}: every output's fit must reach {check.min_fit_pct:g} %")
    return "\n".join(lines)


def plot_check(t_s: np.ndarray, outputs: Sequence[Compared],
               path: str, title: str) -> None:
    """One panel per output, recording and twin over time, the error below them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2 * len(outputs), 1, sharex=True,
                             figsize=(10, 3.2 * len(outputs)), squeeze=False)
    for k, (fit, recorded, twin) in enumerate(outputs):
        n = fit.samples
        top, bottom = axes[2 * k][0], axes[2 * k + 1][0]
        top.plot(t_s[:n], recorded[:n], label="recorded")
        top.plot(t_s[:n], twin[:n], "--", label="twin")
        top.set_ylabel(f"{fit.name} [{fit.unit}]")
        top.set_title(f"{fit.name}: fit {fit_text(fit.fit_pct)}")
        top.legend(loc="upper right")
        bottom.plot(t_s[:n], recorded[:n] - twin[:n], color="tab:red")
        bottom.set_ylabel(f"error [{fit.unit}]")
    axes[-1][0].set_xlabel("t [s]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
