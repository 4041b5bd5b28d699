"""The emulated drives of one lockstep bus stepped as a bank: the steady cycle of every node in
one pass.

A :class:`~hil.emulators.drive.runners.LockstepDrive` hands each master transmission to its
nodes one by one (:meth:`~hil.emulators.drive.node.DriveNode.handle_frames`). In the steady
state of a cyclic synchronous torque run every transmission is the same: each node's RPDO,
then one SYNC; each node latches its RPDO, computes its current, steps its plant, refreshes its
actual values and answers with its TPDOs. :meth:`DriveBank.cycle` does that cycle for all the
nodes in one fused pass, without the dispatch, the latching, the fault and state machinery and
the calls between them - and leaves every node exactly as its own cycle would have (the same
values, states, plant, counters and frames, bit for bit).

It is a fast path for that steady state alone, node by node: a node whose frames or state
differ (a frame it does not expect, not OPERATION ENABLED in CST or not NMT OPERATIONAL, a fault
scheduled or tripping, a changed controlword, a heartbeat or a watchdog due, a load on its
plant...) runs its own path in its turn, the others' cycles around it in node order (as their
frames go out), nothing of it changed before (but, where the bank had stepped its plant, the
plant's input and product buffers, which its own step then writes over). A PDO map the bank
cannot pack sends every node down its own path.

Exactness by construction: each node's current, plant input and actual values are the node's
own Python expressions (the same operations on the same Python floats and ints, in the same
order); the plants step by the plant's own ``dot`` each, or, from :data:`STACK_FROM_NODES`
plants, by one ``matmul`` over the stack of their matrix-vector products, where that is the
same BLAS ``gemv`` per plant (checked when the bank is built: where it is not, each plant's
own ``dot``). Stacked, each plant's state vector lives in the bank's arrays (two rows, swapped
each period as the plant swaps its own buffers), so the plant's own step works on them too.

Cost (this machine, micro-benchmark of ``pump``): ~3 us a cycle plus ~3.8 us a node; a
node's own path is ~8 us for a lone node and ~10 us a node on a shared bus.
"""

from __future__ import annotations

import struct
import time
from collections import deque
from collections.abc import Callable, Sequence
from operator import itemgetter
from typing import Any

import numpy as np

from hil.emulators.drive.cyclic import OVERCURRENT_TRIP, CyclicTorque
from hil.emulators.drive.node import (
    ACTUAL_KEYS,
    CONTROLWORD_KEY,
    DEMAND_POSITION_KEY,
    DEMAND_VELOCITY_KEY,
    INPUTS_KEY,
    POSITION_KEY,
    STATUSWORD_KEY,
    TORQUE_KEY,
    VELOCITY_KEY,
    DriveNode,
    wire_actuals,
)
from hil.emulators.drive.pdo import Pdo
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.drive.states import STATUSWORD
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import CONSUMER_HEARTBEAT, NMT_OPERATIONAL, PRODUCER_HEARTBEAT
from hil.protocols.cia402 import (
    MAX_CURRENT,
    MAX_TORQUE,
    MODES_DISPLAY,
    OPERATION_ENABLED,
    OPERATION_MODES,
    RATED_CURRENT,
    SW_FOLLOWS_COMMAND,
    SW_INTERNAL_LIMIT,
    TARGET_TORQUE,
    TRANSITIONS,
    command_of,
)

#: from this many plants one stacked matrix product costs less than a ``dot`` per plant
STACK_FROM_NODES = 4
#: the struct codes a PDO the bank unpacks or packs may map (integers)
INTEGER_CODES = frozenset("bBhHlLq")
#: the actual values the bank computes each cycle: what its TPDOs may map
MODE_KEY, TARGET_TORQUE_KEY = (MODES_DISPLAY, 0), (TARGET_TORQUE, 0)
RATED_KEY, MAX_TORQUE_KEY, MAX_CURRENT_KEY, TRIP_KEY = \
    (RATED_CURRENT, 0), (MAX_TORQUE, 0), (MAX_CURRENT, 0), (OVERCURRENT_TRIP, 0)
#: what the cycle reads besides the target torque: an RPDO that maps one is not banked
READ_KEYS = (MODE_KEY, RATED_KEY, MAX_TORQUE_KEY, MAX_CURRENT_KEY, TRIP_KEY)
CST = OPERATION_MODES["cst"].code
STEADY_STATUSWORD = STATUSWORD[OPERATION_ENABLED] | SW_FOLLOWS_COMMAND  # CST's bits
LIMITED_STATUSWORD = STEADY_STATUSWORD | SW_INTERNAL_LIMIT
#: the values each actual value takes (what a TPDO field must hold; per turn below 2**31)
ACTUAL_RANGES = {POSITION_KEY: (0, 2**31 - 1), DEMAND_POSITION_KEY: (-(2**31), 2**31 - 1),
                 DEMAND_VELOCITY_KEY: (-(2**31), 2**31 - 1), INPUTS_KEY: (0, 7),
                 VELOCITY_KEY: (-(2**31), 2**31 - 1), TORQUE_KEY: (-32768, 32767),
                 STATUSWORD_KEY: (0, 0xFFFF)}
#: what the bank takes for one node's cycle: its RPDO's values, whether its current was
#: limited, the current applied, the plant's input and the node's time after the cycle
Step = tuple[tuple[int, ...], bool, float, float, int]
#: a node's plant position and velocity after the cycle, and its actual values
Actual = tuple[float, float, tuple[int, ...]]


def integer_codes(pdo: Pdo) -> str | None:
    """``pdo``'s struct codes, one per mapped value, or None when it maps a type the bank does
    not handle."""
    codes = pdo.layout.format.lstrip("<")
    return codes if set(codes) <= INTEGER_CODES else None


def code_range(code: str) -> tuple[int, int]:
    """The values the integer struct ``code`` holds."""
    bits = 8 * struct.calcsize("<" + code)
    return (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if code.islower() else (0, 2**bits - 1)


def picker(indices: Sequence[int]) -> Callable[[tuple[int, ...]], tuple[int, ...]]:
    """The entries ``indices`` of a tuple, as a tuple."""
    if len(indices) == 1:
        index = indices[0]
        return lambda row: (row[index],)
    return itemgetter(*indices)  # type: ignore[return-value]


def stack_matches(plants: Sequence[AxisPlant]) -> bool:
    """Whether one stacked ``matmul`` of the plants' step matrices gives, bit for bit, each
    plant's own product (the same BLAS call on this machine), on a few random state vectors."""
    if len({plant._n for plant in plants}) != 1:
        return False
    matrices = np.stack([plant._step_matrix for plant in plants])
    rng = np.random.default_rng(0)
    for scale in (1e-3, 1.0, 1e6):
        vectors = rng.normal(size=matrices.shape[:2]) * scale
        stacked = np.matmul(matrices, vectors[:, :, None])[:, :, 0]
        for plant, vector, row in zip(plants, vectors, stacked, strict=True):
            if not np.array_equal(plant._step_matrix.dot(vector), row):
                return False
    return True


class BankLayout:
    """What the bank unpacks and packs, for the PDO maps, dispatch tables and mode motions the
    nodes have now (valid while each node's tables are the very objects it was built from)."""

    def __init__(self, nodes: Sequence[DriveNode]) -> None:
        self.tokens = [self.token_of(node) for node in nodes]
        self.ok = False
        rpdos = [self.rpdo_of(node) for node in nodes]
        if any(pdo is None for pdo in rpdos):
            return
        self.rpdos: list[Pdo] = [pdo for pdo in rpdos if pdo is not None]
        first = self.rpdos[0]
        keys = first.keys
        if not integer_codes(first) or any(pdo.keys != keys or pdo.layout.format !=
                                           first.layout.format for pdo in self.rpdos):
            return
        if CONTROLWORD_KEY not in keys or TARGET_TORQUE_KEY not in keys or \
                set(keys) & {*ACTUAL_KEYS, *READ_KEYS} or any(
                    key != CONTROLWORD_KEY and key[0] in node._write_effects
                    for node in nodes for key in keys):
            return  # a key whose writing means more than its value stored, or that it reads
        self.unpack = first.layout.unpack
        self.rpdo_cobs = [pdo.cob_id for pdo in self.rpdos]
        self.rpdo_size = first.layout.size
        self.sync_cobs = [node._sync_cob_id for node in nodes]
        self.cw_index, self.torque_index = keys.index(CONTROLWORD_KEY), \
            keys.index(TARGET_TORQUE_KEY)
        #: what a cycle writes to each node's values: the actual values, then the RPDO's
        self.written_keys = (*ACTUAL_KEYS, *keys)
        transmitters = [node.pdos._transmitters for node in nodes]
        firsts = transmitters[0]
        if any(len(each) != len(firsts) for each in transmitters):
            return
        record, picks, pieces, start = "", [], [], 0
        for j, pdo in enumerate(firsts):
            codes = integer_codes(pdo)
            if codes is None or not set(pdo.keys) <= set(ACTUAL_KEYS) or any(
                    code_range(code)[0] > ACTUAL_RANGES[key][0] or
                    code_range(code)[1] < ACTUAL_RANGES[key][1]
                    for code, key in zip(codes, pdo.keys, strict=True)) or any(
                    each[j].keys != pdo.keys or each[j].layout.format != pdo.layout.format
                    or each[j].trans_type != 1 for each in transmitters):
                return
            record += codes
            picks += [ACTUAL_KEYS.index(key) for key in pdo.keys]
            pieces.append((start, start + pdo.layout.size))
            start += pdo.layout.size
        self.transmitters = transmitters
        #: each node's TPDOs as one record of every TPDO's fields, one TPDO after the other
        self.pack = struct.Struct("<" + record).pack
        self.pick = picker(picks) if picks else None
        #: each node's TPDO frames in its record: (COB-ID, first byte, end)
        self.tpdo_slices = [[(pdo.cob_id, begin, end) for pdo, (begin, end)
                             in zip(each, pieces, strict=True)] for each in transmitters]
        # a node's TPDO heard by another node would reach it within the same transmission
        if any(other is not node and other.hears(pdo.cob_id)
               for node, each in zip(nodes, transmitters, strict=True) for pdo in each
               for other in nodes):
            return
        self.ok = True

    @staticmethod
    def token_of(node: DriveNode) -> tuple[Any, ...]:
        """The tables the layout depends on (each replaced, never changed, when it changes)."""
        pdos = node.pdos
        return (pdos.receivers, node._served, pdos._transmitters, pdos.on_event,
                node.motor.motions)

    @staticmethod
    def rpdo_of(node: DriveNode) -> Pdo | None:
        """The node's one valid synchronous RPDO that its dispatch serves, or None."""
        receivers = node.pdos.receivers
        if len(receivers) != 1 or node._served_receivers is not receivers or \
                node.pdos.on_event:
            return None
        ((cob_id, pdo),) = receivers.items()
        handler = node._served.get(cob_id)
        if pdo.trans_type > 240 or getattr(handler, "args", None) != (pdo,) or \
                node._served.get(node._sync_cob_id) != node._on_sync:
            return None
        motion = node.motor.motions.get(CST)
        return pdo if type(motion) is CyclicTorque else None

    def current(self, nodes: Sequence[DriveNode]) -> bool:
        """Whether the nodes still have the tables this layout was built from."""
        for node, (receivers, served, transmitters, on_event, motions) in zip(
                nodes, self.tokens, strict=True):
            pdos = node.pdos
            if pdos.receivers is not receivers or node._served is not served or \
                    pdos._transmitters is not transmitters or pdos.on_event is not on_event \
                    or node.motor.motions is not motions:
                return False
        return True


class DriveBank:
    """The steady cycle of ``nodes`` (each its own plant), each hearing its bus's ``inboxes``
    (the frames waiting for it), in one pass (:meth:`cycle`)."""

    def __init__(self, nodes: Sequence[DriveNode], inboxes: Sequence[deque[Frame]]) -> None:
        self.nodes, self.inboxes = list(nodes), list(inboxes)
        plants = self.plants = [node.plant for node in nodes]
        if len({id(plant) for plant in plants}) != len(plants):
            raise ValueError("a bank's nodes each have their own plant")
        self.layout: BankLayout | None = None
        self.steady_controlwords: dict[int, bool] = {}
        self.stacked = len(plants) >= STACK_FROM_NODES and stack_matches(plants)
        if not self.stacked:
            return
        count, n = len(plants), plants[0]._n
        self.matrices = np.stack([plant._step_matrix for plant in plants])
        # the plants' two buffers, as rows of the bank's: each plant swaps its own each step
        self.buffers = (np.zeros((count, n + 1)), np.zeros((count, n + 1)))
        self.rows = tuple([buffer[i] for i in range(count)] for buffer in self.buffers)
        self.columns = tuple(buffer[:, :, None] for buffer in self.buffers)
        # the last entry of each plant's buffer: the input it takes, the output it gives
        self.ends = tuple(buffer[:, n] for buffer in self.buffers)
        self._adopt()

    def cycle(self, heard_ns: int | None, own: Callable[[int], None]) -> bool:
        """The transmission waiting in the nodes' inboxes: each node whose waiting frames
        are its RPDO and a SYNC, in the steady state, runs its cycle in the bank's pass (its
        frames taken); each other node, in its turn (node order, as the sends go out), runs
        its own path (``own(i)`` for the ``i``-th node). False, with nothing changed, when no
        node is steady (the caller runs each node's own path)."""
        layout = self.layout
        if layout is None or not layout.current(self.nodes):
            layout = self.layout = BankLayout(self.nodes)
        if not layout.ok:
            return False
        steps = [self._step(layout, node, inbox, rpdo_cob, sync_cob, heard_ns) for node, inbox,
                 rpdo_cob, sync_cob in zip(self.nodes, self.inboxes, layout.rpdo_cobs,
                                           layout.sync_cobs, strict=True)]
        if steps.count(None) == len(steps):
            return False
        outputs = self._products(steps)
        self._commit(layout, heard_ns, steps, self._actuals(steps, outputs), own)
        return True

    def _step(self, layout: BankLayout, node: DriveNode, inbox: deque[Frame], rpdo_cob: int,
              sync_cob: int, heard_ns: int | None) -> Step | None:
        """The node's cycle up to its plant's product (the RPDO decoded, the current as
        MotorLoops.current and CyclicTorque.current compute it, the plant's saturation and
        input as AxisPlant.step's), when it has exactly its RPDO and a SYNC waiting and is in
        the steady state with nothing due this cycle; else None. ``heard_ns``: when the
        transmission was heard (monotonic; None: now), which a node on a master's time with
        a bound judges the master gone by (DriveNode._service)."""
        if len(inbox) != 2:
            return None
        (first_id, first), (second_id, second) = inbox
        if first_id != rpdo_cob or len(first) != layout.rpdo_size or second_id != sync_cob \
                or second:
            return None
        fields = layout.unpack(first)
        cw = fields[layout.cw_index]
        states, plant, values = node.states, node.plant, node._values
        if node.nmt_state != NMT_OPERATIONAL or states.state != OPERATION_ENABLED or \
                node._fault_list or node._delayed or node.pdos.pending or \
                states.comm_warning or states.ramp_start_ns is not None or \
                cw != states.controlword or not (self.steady_controlwords.get(cw) or
                                                 self._steady_controlword(cw)) or \
                not node._sync_timebase or \
                node._steps_per_sync != 1 or plant._configured_load or \
                plant.extra_disturbance_ma or values[MODE_KEY] != CST:
            return None
        gone_ns = node._gone_after_ns
        if gone_ns and heard_ns is not None and time.monotonic_ns() - heard_ns > gone_ns:
            return None  # the master silent past its bound: the node's own path ends its time
        t = node._sync_origin_ns + node._sync_time_ns + node._plant_period_ns
        period_ms = values[(PRODUCER_HEARTBEAT, 0)]
        if period_ms and (node._hb_next_ns is None or t >= node._hb_next_ns):
            return None  # a heartbeat due
        if node._hb_consumer_armed and t - node._hb_last_ns > \
                (values[(CONSUMER_HEARTBEAT, 1)] & 0xFFFF) * 1_000_000:
            return None  # the master's heartbeat lost
        rated = values[RATED_KEY]
        wanted = fields[layout.torque_index] * rated / 1000.0
        if abs(wanted) > values[TRIP_KEY]:
            return None  # the over-current fault
        limit = node.motor.current_limit_ma()
        limited = min(max(wanted, -limit), limit)
        applied = plant.saturated(limited)
        return fields, limited != wanted, applied, applied - plant.axis.u_offset, t

    def _products(self, steps: list[Step | None]) -> list[float]:
        """Each stepping plant's product for one period from its step's input (its buffers'
        product made, not yet swapped): the model's output of each (0.0 for the others,
        whose buffers are left as they are)."""
        outputs = []
        if not self.stacked:
            for plant, step in zip(self.plants, steps, strict=True):
                if step is None:
                    outputs.append(0.0)
                    continue
                xu, z, n = plant._xu, plant._next, plant._n
                xu[n] = step[3]
                plant._step_matrix.dot(xu, out=z)
                outputs.append(z.item(n))
            return outputs
        phase = 0 if self.plants[0]._xu is self.rows[0][0] else 1
        if any(plant._xu is not row for plant, row in zip(self.plants, self.rows[phase],
                                                           strict=True)):
            self._adopt()
            phase = 0
        ends, kept = self.ends[phase], []
        for i, step in enumerate(steps):
            if step is None:  # its input as it is, its product's buffer put back after
                kept.append((i, self.rows[1 - phase][i].copy()))
            else:
                ends[i] = step[3]
        np.matmul(self.matrices, self.columns[phase], out=self.columns[1 - phase])
        for i, row in kept:
            self.rows[1 - phase][i][...] = row
        return self.ends[1 - phase].tolist()  # type: ignore[no-any-return]

    def _adopt(self) -> None:
        """Each plant's buffers made rows of the bank's (their values as they are)."""
        first, second = self.buffers
        for i, plant in enumerate(self.plants):
            state, spare = plant._xu.copy(), plant._next.copy()
            first[i], second[i] = state, spare
            plant._xu, plant._next = self.rows[0][i], self.rows[1][i]

    def _actuals(self, steps: list[Step | None], outputs: list[float]) -> list[Actual | None]:
        """Each stepping node's plant position and velocity after the period (AxisPlant.step)
        and its actual values (DriveNode._refresh_actuals, in ACTUAL_KEYS order); None for a
        node whose values cannot be counted (not finite: its own path reports it)."""
        actuals: list[Actual | None] = []
        for node, plant, step, output in zip(self.nodes, self.plants, steps, outputs,
                                             strict=True):
            if step is None:
                actuals.append(None)
                continue
            position = output + plant.axis.y_offset
            velocity = (position - plant.position_deg) / plant.dt
            per_turn, offset = plant.increments_per_rev, node.motor.count.offset
            try:  # CST's demand: the count now (MotorLoops.demand)
                actuals.append((position, velocity, wire_actuals(
                    position, velocity, per_turn, offset,
                    (position / 360.0 * per_turn + offset, velocity / 360.0 * per_turn),
                    node._switches.inputs(position), step[2], node._values[RATED_KEY],
                    LIMITED_STATUSWORD if step[1] else STEADY_STATUSWORD)))
            except (ValueError, OverflowError):
                actuals.append(None)
        return actuals

    def _steady_controlword(self, cw: int) -> bool:
        """Whether latching ``cw`` again in OPERATION ENABLED changes nothing."""
        steady = self.steady_controlwords.get(cw)
        if steady is None:
            try:
                command = command_of(cw, cw)
            except ValueError:  # no command: the node's own path reports it
                steady = False
            else:
                steady = command is None or not TRANSITIONS.get((OPERATION_ENABLED, command))
            self.steady_controlwords[cw] = steady
        return steady

    def _commit(self, layout: BankLayout, heard_ns: int | None, steps: list[Step | None],
                actuals: list[Actual | None], own: Callable[[int], None]) -> None:
        """Each node in turn: left as its own cycle leaves it, its TPDOs sent; or, where
        the bank has no step for it or a node before it sent it a frame, its own path."""
        heard = time.monotonic_ns() if heard_ns is None else heard_ns
        keys, pack, pick = layout.written_keys, layout.pack, layout.pick
        for i, (node, plant, inbox, rpdo, transmitters, step, actual, slices) in enumerate(zip(
                self.nodes, self.plants, self.inboxes, layout.rpdos, layout.transmitters,
                steps, actuals, layout.tpdo_slices, strict=True)):
            if step is None or actual is None or len(inbox) != 2:
                own(i)
                continue
            fields, active, applied, _, t = step
            position, velocity, values = actual
            inbox.clear()
            node._heard_ns = heard
            rpdo.length_error = False
            node._values.update(zip(keys, (*values, *fields), strict=True))
            node.states.limit_active = active
            plant.applied_current_ma = applied
            plant.velocity_deg_s, plant.position_deg = velocity, position
            plant.steps += 1
            plant._xu, plant._next = plant._next, plant._xu
            node.sync_count += 1
            node._sync_time_ns += node._plant_period_ns
            node._sync_last_ns = t
            node._sync_armed = True
            for pdo in transmitters:
                pdo.counter = 0
            node._serviced = True
            if pick is not None:
                raw = pack(*pick(values))
                node._send([(cob, raw[begin:end]) for cob, begin, end in slices])

