"""The servo paper's figures, redrawn by hil: from the reproduction's sessions (Figs. 5-10,
14-16), from its sweeps (the differences explained), and from the model and the MPC's own
matrices (Figs. 1 and 4). Each function draws one PNG (matplotlib, Agg) and returns nothing.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from hil.controllers.servo.model import StateSpaceModel
from hil.controllers.servo.mpc import reference_expansion
from hil.core.recording.reader import read_session
from hil.paper.report import pyplot, save_figure
from hil.paper.servo_runs import CONTROLLER_TOPIC
from hil.servo.report import draw_waterfall

DPI = 110


def _save(fig: Any, png: str) -> None:
    save_figure(fig, png, DPI)


def horizons(png: str, ht: int = 6, hp: int = 10) -> None:
    """Fig. 1: r(1..H_t|k) and the ERT beyond (FOH and ZOH), from the MPC's own reference
    expansion (the matrix its cost uses), H_t = H_u = 6 and H_p = 10 as in the paper."""
    plt = pyplot()
    i = np.arange(1, hp + 1)
    reference = 2.0 * np.sin(2 * np.pi * i / 16.0)  # a smooth reference ahead of tick k
    known = reference[:ht]
    fig, ax = plt.subplots(figsize=(7, 3.4))
    ax.plot(i, reference, "k:", lw=1, label="reference r(i|k) (unknown beyond H_t)")
    ax.plot(i[:ht], known, "ko", label="r(1..H_t|k): given to the MPC")
    for ert, style in (("foh", "s-"), ("zoh", "^--")):
        extended = reference_expansion(ht, hp, ert) @ known
        ax.plot(i[ht - 2:], extended[ht - 2:], style, lw=1,
                label=f"{ert.upper()}-ERT r̂(i|k)")
    for value, name in ((ht, "H_t = H_u"), (hp, "H_p")):
        ax.axvline(value, color="gray", lw=0.6)
        ax.text(value, ax.get_ylim()[1], f" {name}", va="top", fontsize=8)
    ax.set_xlabel("i (ticks ahead of k)")
    ax.set_ylabel("angle [deg]")
    ax.set_title(f"Fig. 1: horizons and the extended reference, H_t = H_u = {ht}, "
                 f"H_p = {hp}", fontsize=9)
    ax.legend(fontsize=7, loc="lower left")
    _save(fig, png)


def bode(png: str, model: StateSpaceModel, resonance_hz: float) -> None:
    """Fig. 4: the frequency response of the published model, the emulated drive's plant
    (current [mA] to position [deg]), up to the Nyquist frequency."""
    plt = pyplot()
    hz = np.logspace(0, np.log10(0.5 / model.dt) - 1e-3, 800)
    z = np.exp(2j * np.pi * hz * model.dt)
    eye = np.eye(model.n_states)
    response = np.array([(model.C @ np.linalg.solve(zk * eye - model.A, model.B)).item()
                         for zk in z])
    fig, (mag, phase) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    mag.semilogx(hz, 20 * np.log10(np.abs(response)))
    phase.semilogx(hz, np.degrees(np.unwrap(np.angle(response))))
    for ax in (mag, phase):
        ax.axvline(resonance_hz, color="r", lw=0.6, ls=":")
        ax.grid(True, which="both", alpha=0.3)
    mag.set_ylabel("magnitude [dB deg/mA]")
    phase.set_ylabel("phase [deg]")
    phase.set_xlabel("frequency [Hz]")
    mag.set_title(f"Fig. 4: the published headstock model (T = {model.dt * 1e6:g} us), "
                  f"resonance {resonance_hz:.0f} Hz", fontsize=9)
    _save(fig, png)


def tracking(png: str, title: str, mcap: str, settle_s: float,
             others: Mapping[str, str] | None = None) -> None:
    """Figs. 5, 6, 15: reference and position, then the tracking error, of one session;
    ``others`` (label -> session) adds their errors, dashed."""
    plt = pyplot()
    command = read_session(mcap).arrays("/drive/command")
    t, reference, error = command["t_s"], command["reference_deg"], command["error_deg"]
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    top.plot(t, reference, "k--", lw=1, label="reference")
    top.plot(t, reference + error, lw=1, label="position")
    top.set_ylabel("angle [deg]")
    top.legend(fontsize=8, loc="best")
    bottom.plot(t, error, lw=0.9, label="error")
    for label, other in (others or {}).items():
        more = read_session(other).arrays("/drive/command")
        bottom.plot(more["t_s"], more["error_deg"], "--", lw=0.8, label=label)
    if others:
        bottom.legend(fontsize=8, loc="best")
    for ax in (top, bottom):
        ax.axvspan(settle_s, t[-1], color="0.92", zorder=0)
    bottom.axhline(0.0, color="k", lw=0.5)
    bottom.set_ylabel("position - reference [deg]")
    bottom.set_xlabel("time [s] (shaded: where the KPIs are measured)")
    top.set_title(title, fontsize=9)
    _save(fig, png)


def normalised_errors(png: str, panels: Sequence[Mapping[str, Any]]) -> None:
    """Figs. 7-8: per case, the cumulative |error| over the measured cycle against H_t,
    normalised to set-point MPC (ZOH, H_t = 1), with the PID's as a line."""
    plt = pyplot()
    fig, axes = plt.subplots(1, len(panels), figsize=(4.4 * len(panels), 3.6), squeeze=False)
    for ax, panel in zip(axes[0], panels, strict=True):
        for ert, style in (("zoh", "o-"), ("foh", "s-")):
            rows = [row for row in panel["mpc"] if row["ert"] == ert]
            ax.plot([row["ht"] for row in rows], [row["normalised"] for row in rows], style,
                    label=f"MPC {ert.upper()}-ERT")
        ax.axhline(panel["pid"]["normalised"], color="k", ls="--", label="cascaded PID")
        ax.set_yscale("log")
        ax.set_xlabel("trajectory horizon H_t = H_u")
        ax.set_title(f"{panel['figure']}: {panel['title']}", fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylabel("cumulative |error|, set-point MPC = 1")
    axes[0, 0].legend(fontsize=8)
    _save(fig, png)


def waterfalls(png: str, sessions: Mapping[str, str]) -> None:
    """Figs. 9-10: the predicted inputs of every recorded tick (thin) over the applied
    current (thick), one panel per session (label -> file)."""
    plt = pyplot()
    fig, axes = plt.subplots(len(sessions), 1, figsize=(8, 3.2 * len(sessions)), squeeze=False)
    for ax, (label, mcap) in zip(axes[:, 0], sessions.items(), strict=True):
        data = read_session(mcap)
        command, prediction = data.arrays("/drive/command"), data.arrays("/mpc/prediction")
        draw_waterfall(ax, command, prediction, int(command["log_time_ns"][0]))
        ax.set_title(label, fontsize=9)
    axes[-1, 0].set_xlabel("time [s]")
    _save(fig, png)


def explicit_run(png: str, title: str, mcap: str, limit_ma: float,
                 push: tuple[float, float] | None = None) -> None:
    """Figs. 14 and 16: position and reference, tracking error, current, and the explicit
    MPC's controller of every tick (``/empc/controller``: 1 the unconstrained law)."""
    plt = pyplot()
    data = read_session(mcap)
    command, used = data.arrays("/drive/command"), data.arrays(CONTROLLER_TOPIC)
    t = command["t_s"]
    fig, axes = plt.subplots(4, 1, figsize=(8, 8), sharex=True)
    axes[0].plot(t, command["reference_deg"], "k--", lw=1, label="reference")
    axes[0].plot(t, command["reference_deg"] + command["error_deg"], lw=1, label="position")
    axes[0].legend(fontsize=8)
    axes[0].set_ylabel("angle [deg]")
    axes[1].plot(t, command["error_deg"], lw=0.9)
    axes[1].set_ylabel("error [deg]")
    axes[2].plot(t, command["command_mA"], lw=0.9)
    for sign in (1, -1):
        axes[2].axhline(sign * limit_ma, color="r", lw=0.6, ls=":")
    axes[2].set_ylabel("current [mA]")
    axes[3].step(used["t_s"], used["controller"], where="post", lw=0.9)
    axes[3].set_ylabel("controller #")
    axes[3].set_xlabel("time [s]")
    if push is not None:
        for ax in axes:
            ax.axvspan(*push, color="0.9", zorder=0)
    axes[0].set_title(title, fontsize=9)
    _save(fig, png)


def explanations(png: str, panels: Sequence[Mapping[str, Any]]) -> None:
    """The sweeps that explain a difference: per panel, hil's measured points against the
    swept value, and the paper's figure as a horizontal line."""
    plt = pyplot()
    columns = 3
    rows = -(-len(panels) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(4.4 * columns, 3.6 * rows), squeeze=False)
    for ax in axes.flat[len(panels):]:
        ax.set_axis_off()
    for ax, panel in zip(axes.flat, panels, strict=False):
        ax.plot(panel["x"], panel["y"], "o-", label="hil")
        ax.axhline(panel["paper"], color="r", ls="--", label=f"paper: {panel['paper']:g}")
        if panel.get("logx"):
            ax.set_xscale("log")
        if panel.get("logy"):
            ax.set_yscale("log")
        ax.set_xlabel(panel["xlabel"])
        ax.set_ylabel(panel["ylabel"])
        ax.set_title(panel["title"], fontsize=9)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    _save(fig, png)
