"""The servo tick: one loop task at the base period T (`master.cycle_period_us`, 500 us by
default), in the loop's four phases.

* **read** - ``master.receive_feedback()``: the TPDOs of the SYNC the previous tick sent. In
  real time they travelled while the loop slept; in lockstep the emulated drive answered the
  SYNC at once on the in-process bus, so they are waiting. One form for both clocks.
* **compute** - the controller's ``step(y_k, t_k)`` gives u_k (guarded, timed): a current, or
  where the drive closes its own loop (CSP, CSV, PV) a position or a velocity, as the
  controller's :class:`~hil.controllers.base.Output` says.
* **write** - ``master.send_set_point(u_k)``: RPDO + SYNC. The drive applies u_k on that SYNC
  and its TPDOs report y_{k+1}, exactly the offline simulation's ``x(k+1) = A x(k) + B u(k)``.
* **record** - ``/drive/command``, ``/drive/feedback``, ``/mpc/prediction``, the KPIs and the
  per-tick limits, after the command has left (in real time the drive's answer travels while
  the tick is logged).

The reference is placed where the axis stands when the task is built (the drive enabled,
before the first step: :class:`~hil.controllers.servo.references.PlacedReference`), and the
error the KPIs, the safety net and the limits see is multi-turn: position - reference, turns
included. The controller is given the position its contract asks for
(:func:`~hil.controllers.base.position_input_of`): ``position % 360`` by default, or multi-turn.
After the ticks, each cycle of the drive's safe stop (quick stop until the axis stands, then
disable voltage) is recorded on ``/drive/stop``.

The controller's time is the tick's slot on the schedule grid (k T), in real time too: a
skipped tick skips its reference sample. With the emulated drive the plant only moves on SYNC,
so a skipped tick also freezes the plant for one period (a real drive holds its last command).
In lockstep runs up to ``PREDICTION_EVERY_TICK_UP_TO_S`` the prediction is recorded every
tick, otherwise every ``PREDICTION_EVERY_REALTIME``-th tick by default (200 Hz).
"""

from __future__ import annotations

import math

import numpy as np

from hil.controllers.base import (
    CURRENT,
    OUTPUT_UNITS,
    UNWRAPPED,
    Predicting,
    ReportsEvents,
    ServoController,
    horizons_of,
    output_of,
    position_input_of,
    solver_of,
)
from hil.controllers.servo.references import PlacedReference, ReferenceSamples, Scenario
from hil.core.guard import guarded_call
from hil.core.loop import Task
from hil.core.session import Session
from hil.core.verdict import SignalWatch
from hil.drivers.canopen import CanDriveMaster, Feedback, SdoAbortError
from hil.drivers.canopen.identity import not_hil_emulator, read_identity
from hil.errors import ControllerError, UsageError
from hil.servo.safety import SafetyMonitor
from hil.servo.topics import FEEDBACK_SCHEMA, PREDICTION_SCHEMA, STOP_SCHEMA, command_schema
from hil.servo.tracking import TrackingStats

PREDICTION_EVERY_REALTIME = 10  # 200 Hz of /mpc/prediction in real time and in long runs
PREDICTION_EVERY_TICK_UP_TO_S = 60.0  # lockstep runs up to this long record it every tick
DISTURBANCE_OBJECT = 0x2003  # the emulated drive's external disturbance torque [mA], INTEGER16
#: hil's emulated drive's object the disturbance scenario pushes the axis through
DISTURBANCE_TEXT = "0x2003 disturbance torque"
NUMBERS = (int, float, np.number)  # what a step may return (built once: checked every tick)


class ServoTask(Task):
    """read feedback -> controller step -> write command -> record the tick.

    Built once the drive is enabled: it places ``reference`` (the controller's) where the
    axis stands, and records the drive's safe stop."""

    def __init__(self, session: Session, master: CanDriveMaster, controller: ServoController,
                 scenario: Scenario, *, reference: PlacedReference, label: str,
                 settle_s: float, prediction_every: int, budget_s: float | None,
                 safety: SafetyMonitor, watch: SignalWatch | None = None,
                 axis: str | None = None) -> None:
        super().__init__("servo" if axis is None else f"servo-{axis}")
        self.axis = axis
        self.session, self.master, self.controller = session, master, controller
        self.scenario = scenario
        self.loop = session.loop
        self.clock = session.clock
        self.realtime = session.clock.mode == "realtime"
        self.period_ns = self.loop.base_period_ns
        self.dt = self.period_ns / 1e9
        self.reference_offset_deg = self._place(reference, axis)
        self.reference = ReferenceSamples(reference, self.dt)
        self.unwrapped = position_input_of(controller) == UNWRAPPED
        # a current, or a set point for a drive that closes its own loop
        self.output = output_of(controller)
        self.currents = self.output == CURRENT
        self.stats = TrackingStats(settle_s)
        self.prediction_every = prediction_every
        self.label = label
        self.budget_s = budget_s
        self.watch = watch if watch is not None and watch.limits else None
        self.safety = safety
        self.controller_changed()
        # one axis: /drive/command, /drive/feedback, /mpc/prediction; several: /axis/NAME/...
        drive, mpc = ("/drive", "/mpc") if axis is None else (f"/axis/{axis}",) * 2
        self.commands = session.topic(f"{drive}/command", command_schema(self.output),
                                      high_rate=True)
        self.feedbacks = session.topic(f"{drive}/feedback", FEEDBACK_SCHEMA, high_rate=True)
        self.predictions = (session.topic(f"{mpc}/prediction", PREDICTION_SCHEMA, high_rate=True)
                            if self.predictor is not None else None)
        self.stops = session.topic(f"{drive}/stop", STOP_SCHEMA, high_rate=True)
        self._stop_ns = 0
        master.on_stop_cycle = self._record_stop_cycle
        self._disturbance_ma = 0
        self._last_path = ""
        # this tick: its number and time, the feedback read, the command and its compute time
        self._tick = 0
        self._t_s = 0.0
        self._feedback: Feedback | None = None
        self._command = 0.0
        self._compute_us = 0.0
        self._error = 0.0    # position - reference [deg] (rows)
        self._applied = 0.0  # the current the drive was sent, or reports [mA] (rows)
        self.late_writes = 0
        self.stale = 0

    @property
    def feedback(self) -> Feedback:
        """This tick's feedback (after the read phase)."""
        assert self._feedback is not None
        return self._feedback

    @property
    def t_s(self) -> float:
        """This tick's time on the schedule grid [s] (after the compute phase)."""
        return self._t_s

    def prime(self) -> None:
        """In real time, one axis: a first cycle that holds the axis, its answer waited for
        before the clock starts (a drive's first answer comes late)."""
        if self.realtime and self.axis is None:
            self.master.prime()

    def read(self, t_ns: int) -> None:
        self._feedback = self.master.receive_feedback()

    def compute(self, t_ns: int) -> None:
        """The controller's step only: the tick is recorded after the command has left."""
        n = self.loop.tick_number  # its slot's, late or not: (t_ns - start) // T may be the next
        self.compute_at(n, n * self.dt)

    def compute_at(self, n: int, t_s: float) -> None:
        """:meth:`compute` of tick ``n`` at ``t_s`` (``n * dt``: the axes' task works it out
        once for them all). A raise, a command that is not a finite number or a step over
        budget is a ControllerError (on ``/events`` too)."""
        feedback = self._feedback
        assert feedback is not None
        self._tick, self._t_s = n, t_s
        position = feedback.position_deg
        if not self.unwrapped:
            position %= 360.0
        try:
            u, elapsed = guarded_call(self.label, "step", self.controller.step, position, t_s,
                                      budget_s=self.budget_s)
            if u.__class__ is not float or u - u != 0.0:  # not a finite float: checked in full
                u = self._command_of(u)
        except ControllerError as exc:
            self.session.event("controller.error", str(exc), level="error",
                               source="controller", t_s=t_s)
            raise
        self._command, self._compute_us = u, elapsed * 1e6

    def write(self, t_ns: int) -> None:
        """RPDO + SYNC (and the scenario's disturbance torque, applied from that SYNC on)."""
        if self.scenario.disturbance is not None:
            self._inject_disturbance(self._disturbance_for(self._t_s))
        self.master.send_set_point(self._command)
        if self.realtime and \
                self.clock.time_ns() > self.loop.start_ns + (self._tick + 1) * self.period_ns:
            self.late_writes += 1

    def record(self, t_ns: int) -> None:
        """KPIs, /drive/feedback, /drive/command, limits and the MPC prediction of this tick."""
        feedback_row, command_row = self.rows()
        self.feedbacks.log(t_ns, feedback_row)
        self.commands.log(t_ns, command_row)
        self.check(t_ns)

    def rows(self) -> tuple[tuple[object, ...], tuple[object, ...]]:
        """This tick in the KPIs, and its rows of ``feedbacks`` and ``commands`` (packed, in
        the order of FEEDBACK_SCHEMA and command_schema; None: left out), for :meth:`record`
        to log, or the bus's task with every axis' in one hand-over; :meth:`check` next."""
        feedback, n, t_s, u = self._feedback, self._tick, self._t_s, self._command
        assert feedback is not None
        position, fresh = feedback.position_deg, feedback.fresh
        r = self.reference(n)
        self._error = error = position - r
        if not fresh:
            self.stale += 1
        disturbance = self._disturbance_for(t_s) if self.scenario.disturbance is not None \
            else None
        path = self._solver_path() if self._paths else None
        feedback_row = (position, feedback.velocity_deg_s, feedback.current_ma,
                        feedback.command_ma, feedback.statusword, feedback.cycle,
                        fresh, feedback.rtt_us)
        compute_us = self._compute_us
        if self.currents:  # the current the drive is sent; the request on /drive/command
            # u is finite (compute_at): the master's clamp
            self._applied = applied = self.master.applied_current(u)
            self.stats.add(t_s, error, applied, compute_us, u)
            return feedback_row, (t_s, r, error, u, disturbance, compute_us, path or None)
        # the drive chooses the current: the KPIs take the one it reports
        self._applied = applied = feedback.current_ma
        self.stats.add(t_s, error, applied, compute_us)
        return feedback_row, (t_s, r, error, math.nan, disturbance, compute_us, path or None,
                              u)

    def check(self, t_ns: int, late_us: float | None = None) -> None:
        """This tick's safety limits and ``--limit`` signals (after :meth:`rows`), and its MPC
        prediction. ``late_us``: the loop's lateness of this tick (None: worked out here; the
        axes' task works it out once for them all, :meth:`late_us`)."""
        feedback, n, t_s = self._feedback, self._tick, self._t_s
        assert feedback is not None
        error = self._error
        if late_us is None:
            late_us = self.late_us(t_ns)
        stop = self.safety.check(t_s, error, feedback.position_deg, feedback.velocity_deg_s,
                                 feedback.fresh, feedback.rtt_us, late_us)
        if stop is not None:
            self.session.event("safety.stop", stop, level="error", source="safety", t_s=t_s)
            self.loop.stop(stop)
        if self.watch is not None:
            self._check_limits(error, self._applied, feedback)
        if self.predictor is not None and self.predictions is not None \
                and n % self.prediction_every == 0:
            u_pred, y_pred = self.predictor.prediction()
            # as lists: cheaper to hand over than arrays; the writer process encodes them
            # (CDR float32 by default)
            self.predictions.log(t_ns, (t_s, u_pred[: self.hu].tolist(), y_pred.tolist()))

    def late_us(self, t_ns: int) -> float:
        """The loop's lateness of this tick, started at ``t_ns`` [us]."""
        return (t_ns - self.loop.start_ns - self._tick * self.period_ns) / 1e3

    def controller_changed(self) -> None:
        """Read again what the task keeps of its controller (after a rebuild swapped its
        horizons or solver in, at a tick boundary)."""
        controller = self.controller
        horizons = horizons_of(controller)
        self.hu = horizons.hu if horizons is not None else None
        self.solver = solver_of(controller)
        self.predictor = controller if isinstance(controller, Predicting) else None
        # decided here: a runtime-checkable Protocol's isinstance costs microseconds a tick
        self.event_source = controller if isinstance(controller, ReportsEvents) else None
        # a path to record (or events to report) each tick; else the row's path is None
        self._paths = self.solver is not None or self.event_source is not None
        if not self._paths:
            self._last_path = ""

    # -- helpers -----------------------------------------------------------------------
    def _place(self, reference: PlacedReference, axis: str | None) -> float:
        """The reference placed where the axis stands now (the feedback of the enable), before
        the first step; where and how in the session's ``reference`` metadata. Returns the
        reference's offset [deg]."""
        start = self.master.feedback
        assert start is not None, "the servo task is built once the drive is enabled"
        offset = reference.place(start.position_deg)
        self.session.recorder.metadata("reference" if axis is None else f"reference/{axis}", {
            "start_deg": repr(start.position_deg), "offset_deg": repr(offset),
            "placed": "from here" if reference.relative else
            "absolute (homed)" if reference.absolute else "on the nearest turn"})
        return offset

    def _record_stop_cycle(self, feedback: Feedback) -> None:
        """One cycle of the drive's safe stop, on ``/drive/stop``: stamped with the session
        clock in real time; in lockstep, where that clock stands still after the last tick,
        one period (the drive's SYNC) after the tick or the cycle before."""
        now = self.clock.time_ns()
        self._stop_ns = now if self.realtime else max(now, self._stop_ns) + self.period_ns
        self.stops.log(self._stop_ns, (feedback.position_deg, feedback.velocity_deg_s,
                                       feedback.current_ma, feedback.statusword,
                                       feedback.cycle, feedback.fresh))

    def _command_of(self, u: object) -> float:
        """A step's ``u`` that is not a plain finite float: as a float, or a ControllerError
        when it is not a finite number."""
        if isinstance(u, bool) or not isinstance(u, NUMBERS) or not math.isfinite(u):
            raise ControllerError(
                f"controller {self.label!r}: step() must return a finite {self.output} in "
                f"{OUTPUT_UNITS[self.output]}, got {type(u).__name__} {u!r:.60}")
        return float(u)

    def _check_limits(self, error: float, command: float, feedback: Feedback) -> None:
        assert self.watch is not None
        violation = self.watch.check({"abs_error_deg": abs(error),
                                      "abs_command_mA": abs(command),
                                      "abs_velocity_deg_s": abs(feedback.velocity_deg_s),
                                      "position_deg": feedback.position_deg})
        if violation is not None:
            self.session.event("limit.abort", f"limit violated, run stopped: "
                               f"{violation.describe()}", level="error", source="limits",
                               limit=str(violation.limit), measured=violation.measured,
                               t_s=self._t_s)
            self.loop.stop(f"limit {violation.limit}")

    def _disturbance_for(self, t_s: float) -> int:
        return round(self.scenario.disturbance(t_s)) if self.scenario.disturbance else 0

    def _inject_disturbance(self, value: int) -> None:
        """Scenario torque through the emulated drive's 0x2003 (an SDO download queued for
        this cycle's frames, ahead of its SYNC; only on a change): applied from that SYNC on,
        i.e. while u(k) is, as in the offline simulation. No SDO round trip in the cycle."""
        if value == self._disturbance_ma:
            return
        self.master.sdo.queue_write(DISTURBANCE_OBJECT, 0, value, "<h")
        self._disturbance_ma = value
        self.session.event("servo.disturbance", f"disturbance torque {value} mA",
                           source="scenario", torque_mA=value, t_s=self._t_s)

    def _solver_path(self) -> str:
        """This tick's solver path (MPCs); the explicit MPC's fallback events, or the online
        MPC's first fallback of a run of them, on ``/events``."""
        path = self.solver.last_path if self.solver is not None else ""
        if self.event_source is not None:  # the explicit MPC reports its fallbacks
            for event in self.event_source.pop_events():
                event = dict(event)
                kind, message = event.pop("kind"), event.pop("message")
                level = event.pop("level", "warning")
                self.session.event(f"empc.{kind.removeprefix('empc_')}", message, level=level,
                                   source="empc", **event)
        elif path == "fallback" and self._last_path != "fallback":
            self.session.event("mpc.fallback", "MPC: the QP had no solution (infeasible "
                               "constraints): solved without the output constraints or held "
                               "the input", level="warning", source="mpc", t_s=self._t_s)
        self._last_path = path
        return path


def check_disturbance_object(master: CanDriveMaster) -> None:
    """The disturbance scenario pushes the axis through hil's emulated drive's 0x2003, a
    manufacturer object: the drive must be hil's emulator (its 0x1018), and take it (a twin
    whose file has an object of its own there does not). Else one UsageError line."""
    identity = read_identity(master.sdo)
    if not identity.hil_emulator:
        raise UsageError("the disturbance scenario pushes the axis through hil's emulated "
                         f"drive's {DISTURBANCE_TEXT}: "
                         f"{not_hil_emulator(master.node_id, identity, DISTURBANCE_TEXT)}")
    try:
        master.sdo.write(DISTURBANCE_OBJECT, 0, 0, "<h")
    except SdoAbortError as exc:
        raise UsageError(
            f"the disturbance scenario needs the emulated drive's {DISTURBANCE_TEXT} object "
            f"(a test hook), which this drive refuses: {exc}") from None
