"""The energy paper's figures redrawn from hil's sessions (PNG, matplotlib): the models'
validation (Figs. 3a, 3b), the profiles against H_p (Fig. 3c), EEC against BC (Figs. 4a-c, 5),
the unexpected load (Fig. 6), and the J1 sensitivity study."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hil.paper.energy_measures import RunSignals
from hil.paper.energy_runs import Identified
from hil.paper.report import pyplot, save_figure

DPI = 100
VALIDATION_S = 60.0   # Figs. 3a-b show the last minute of the held-out record


def _save(fig: Any, path: Path) -> Path:
    return save_figure(fig, path, DPI)


@dataclass(frozen=True)
class Labelled:
    """A run's signals with its label in the figures, up to ``end_s``."""

    label: str
    signals: RunSignals
    end_s: float

    def power(self) -> tuple[np.ndarray, np.ndarray]:
        inside = self.signals.t < self.end_s
        return self.signals.t[inside], self.signals.va[inside]


def validation(models: Sequence[Identified], path: Path) -> Path:
    """Figs. 3a-b: each model's inputs and its output against the measured one over the last
    minute of the held-out record."""
    plt = pyplot()
    fig, axes = plt.subplots(2, len(models), figsize=(6.5 * len(models), 5.2), squeeze=False,
                             gridspec_kw={"height_ratios": [1, 2.5]}, sharex="col")
    for column, model in enumerate(models):
        keep = model.t_s >= model.t_s[-1] - VALIDATION_S
        t = model.t_s[keep]
        for k, name in enumerate(model.model.inputs):
            if not name.endswith("_start"):
                axes[0, column].step(t, model.u[keep, k] + 1.2 * (k // 2), where="post",
                                     lw=0.9, label=name.rpartition(":")[2])
        axes[0, column].set_title(f"{model.name}: inputs (PRBS)")
        axes[0, column].legend(loc="upper right", fontsize=7)
        axes[0, column].set_yticks([])
        axes[1, column].plot(t, model.y[keep], lw=0.7, color="tab:gray", label="measured")
        fit = f"N4SID, order 3 (held-out fit {model.model.fit_pct:.2f} %)"
        axes[1, column].plot(t, model.model.simulate(model.u)[keep, 0], lw=1.0,
                             color="tab:blue", label=fit)
        axes[1, column].set_ylabel("S (phase L2) [VA]")
        axes[1, column].set_xlabel("time [s]")
        axes[1, column].legend(loc="upper right", fontsize=7)
    return _save(fig, path)


def profiles(runs: Sequence[Labelled], path: Path, title: str) -> Path:
    """Fig. 3c: the total apparent power of each run, overlaid."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(11, 3.8))
    for run in runs:
        t, va = run.power()
        ax.plot(t, va, lw=0.7, label=f"{run.label} (J2 {va.max():.0f} VA)")
    ax.set_title(title)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("S [VA]")
    ax.legend(loc="upper right", fontsize=8)
    return _save(fig, path)


def power_rows(runs: Sequence[Labelled], path: Path, title: str,
               limit: float | None = None) -> Path:
    """Figs. 4a, 5, 6a: the total apparent power of each run on a row of its own, its peak
    (J2) dashed."""
    plt = pyplot()
    fig, axes = plt.subplots(len(runs), 1, figsize=(11, 1.9 * len(runs) + 0.6), sharex=True,
                             sharey=True, squeeze=False)
    for ax, run in zip(axes[:, 0], runs, strict=True):
        t, va = run.power()
        ax.plot(t, va, lw=0.6, color="tab:blue")
        ax.axhline(va.max(), lw=0.8, ls="--", color="tab:red")
        if limit is not None:
            ax.axhline(limit, lw=0.8, ls=":", color="tab:gray")
        ax.set_title(f"{run.label}: J2 = {va.max():.1f} VA", fontsize=9, loc="left")
        ax.set_ylabel("S [VA]")
    axes[0, 0].figure.suptitle(title, fontsize=10)
    axes[-1, 0].set_xlabel("time [s]")
    return _save(fig, path)


def relay_rows(runs: Sequence[Labelled], path: Path) -> Path:
    """Fig. 4b: u_P1 and u_P2 of each run."""
    plt = pyplot()
    fig, axes = plt.subplots(len(runs), 1, figsize=(11, 1.5 * len(runs) + 0.5), sharex=True,
                             squeeze=False)
    for ax, run in zip(axes[:, 0], runs, strict=True):
        s = run.signals
        inside = s.relay_t < run.end_s
        for k, name in enumerate(("P1", "P2")):
            ax.step(s.relay_t[inside], s.relays[name][inside] * 0.8 + 1.2 * k, where="post",
                    lw=0.9, label=name)
        ax.set_yticks([0.4, 1.6], ["u_P1", "u_P2"])
        ax.set_title(run.label, fontsize=9, loc="left")
    axes[-1, 0].set_xlabel("time [s]")
    return _save(fig, path)


def level_rows(runs: Sequence[Labelled], bounds: Mapping[str, tuple[float, float]],
               path: Path) -> Path:
    """Fig. 4c: q_1 and q_2 of each run against their operating range."""
    plt = pyplot()
    fig, axes = plt.subplots(len(bounds), 1, figsize=(11, 2.6 * len(bounds)), sharex=True,
                             squeeze=False)
    for ax, (name, (low, high)) in zip(axes[:, 0], bounds.items(), strict=True):
        for run in runs:
            s = run.signals
            inside = s.level_t < run.end_s
            ax.plot(s.level_t[inside], s.levels[name][inside], lw=0.9, label=run.label)
        for bound in (low, high):
            ax.axhline(bound, lw=0.8, ls=":", color="black")
        ax.set_ylabel(name)
        ax.legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("time [s]")
    return _save(fig, path)


def disturbance(runs: Sequence[Labelled], scheduled: tuple[np.ndarray, np.ndarray],
                path: Path) -> Path:
    """Fig. 6: (a) the total apparent power of each run; (b) the unexpected load as
    scheduled and as the EEC's Kalman filter estimated it."""
    plt = pyplot()
    fig, axes = plt.subplots(len(runs) + 1, 1, figsize=(11, 1.9 * (len(runs) + 1) + 0.6),
                             sharex=True, squeeze=False)
    for ax, run in zip(axes[:-1, 0], runs, strict=True):
        t, va = run.power()
        ax.plot(t, va, lw=0.6, color="tab:blue")
        ax.axhline(va.max(), lw=0.8, ls="--", color="tab:red")
        ax.set_title(f"(a) {run.label}: J2 = {va.max():.1f} VA", fontsize=9, loc="left")
        ax.set_ylabel("S [VA]")
    ax = axes[-1, 0]
    ax.step(*scheduled, where="post", color="black", lw=1.0, label="load as scheduled")
    for run in runs:
        s = run.signals
        if s.estimate_t.size:
            inside = s.estimate_t < run.end_s
            ax.plot(s.estimate_t[inside], s.disturbance_va[inside], lw=0.8,
                    label=f"{run.label}: Kalman estimate")
    ax.set_title("(b) the unknown input", fontsize=9, loc="left")
    ax.set_ylabel("VA")
    ax.set_xlabel("time [s]")
    ax.legend(loc="upper right", fontsize=7)
    return _save(fig, path)


@dataclass(frozen=True)
class Panel:
    """One knob of the sensitivity study: its label, values (x tick labels), the J1 gain and
    the level-adjusted J1 gain of the EEC over BC at each [%] (None where not run)."""

    label: str
    values: Sequence[str]
    gain: Sequence[float | None]
    adjusted: Sequence[float | None]
    baseline: int | None = None   # the index of the paper's condition


def sensitivity(panels: Sequence[Panel], paper_gains: Mapping[str, float], path: Path
                ) -> Path:
    """The J1 sensitivity study: per knob, the EEC's J1 gain over BC and the same with the
    resource left in the tanks taken out, against the paper's gains."""
    plt = pyplot()
    columns = 2
    rows = -(-len(panels) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(12, 2.9 * rows), squeeze=False)
    for ax, panel in zip(axes.flat, panels, strict=False):
        x = np.arange(len(panel.values))
        gain = np.array([np.nan if v is None else v for v in panel.gain], dtype=float)
        adjusted = np.array([np.nan if v is None else v for v in panel.adjusted], dtype=float)
        ax.plot(x, gain, "o-", color="tab:blue", label="J1 gain")
        ax.plot(x, adjusted, "s--", color="tab:green", label="at equal levels")
        if panel.baseline is not None:
            ax.axvline(panel.baseline, color="tab:gray", lw=0.8, ls=":")
        for label, value in paper_gains.items():
            ax.axhline(value, color="tab:red", lw=0.6, ls="-.")
            ax.annotate(label, (x[-1], value), fontsize=6, color="tab:red",
                        xytext=(2, 1), textcoords="offset points")
        ax.axhline(0.0, color="black", lw=0.5)
        ax.set_xticks(x, panel.values, fontsize=7)
        ax.set_title(panel.label, fontsize=9)
        ax.set_ylabel("EEC vs BC [%]", fontsize=8)
    for ax in list(axes.flat)[len(panels):]:
        ax.axis("off")
    axes[0, 0].legend(loc="upper left", fontsize=7)
    return _save(fig, path)
