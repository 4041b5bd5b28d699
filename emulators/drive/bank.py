"""The emulated drives of one lockstep bus stepped as a bank: the steady cycle of every node at
once, on arrays.

A :class:`~hil.emulators.drive.runners.LockstepDrive` hands each master transmission to its
nodes one by one (:meth:`~hil.emulators.drive.node.DriveNode.handle_frames`). In the steady
state of a cyclic synchronous torque run every transmission is the same: each node's RPDO,
then one SYNC; each node latches its RPDO, computes its current, steps its plant, refreshes its
actual values and answers with its TPDOs. :meth:`DriveBank.cycle` does that cycle for all the
nodes together - the RPDOs decoded with one numpy dtype, the currents and limits on arrays,
the plants stepped by one stacked matrix product, the actual values on arrays, the TPDOs
packed from structured arrays and sliced into frames - and leaves every node exactly as its
own cycle would have (the same values, states, plant, counters and frames, bit for bit).

It is a fast path for that steady state alone: whenever anything differs (a frame it does not
expect, a node not OPERATION ENABLED in CST or not NMT OPERATIONAL, a fault scheduled or
tripping, a changed controlword, a heartbeat or a watchdog due, a PDO map it cannot pack, a
load on a plant...) it declines before changing anything, and the nodes run their own path.

Exactness: the elementwise float64 operations are those of the node's Python (``+ - * /``,
comparisons, ``round`` as ``rint``: both round half to even); the integers it computes
(increments, wrapped and clamped) are held as floats below 2**53, where every sum, remainder
and bound is exact, and the bank declines beyond; ``max``/``min`` of the current only where
no two zeros tie (numpy's pick of -0.0 or +0.0 is not Python's: a limit of 0 declines); the
plants' products are one ``matmul`` over a stack of matrix-vector products, each the same BLAS
``gemv`` the plant calls (checked when the bank is built: where it is not, there is no bank).
Each plant's state vector lives in the bank's arrays (two rows, swapped each period as the
plant swaps its own buffers), so the plant's own step, between bank cycles, works on them.

Cost (this machine, quickest of 5, micro-benchmark of ``pump``): ~20 us a cycle whatever the
number of nodes (some 45 numpy calls at 0.2-0.7 us each) plus ~2-3 us a node (the checks,
each node's values written back, its frames sent); a node's own path is ~10 us a node.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Sequence
from operator import itemgetter
from typing import Any

import numpy as np

from hil.emulators.drive.cyclic import OVERCURRENT_TRIP, CyclicTorque
from hil.emulators.drive.node import (
    CONTROLWORD_KEY,
    DEMAND_POSITION_KEY,
    DEMAND_VELOCITY_KEY,
    INPUTS_KEY,
    POSITION_KEY,
    STATUSWORD_KEY,
    TORQUE_KEY,
    VELOCITY_KEY,
    DriveNode,
)
from hil.emulators.drive.pdo import Pdo
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.drive.states import STATUSWORD
from hil.protocols.can_frames import Frame
from hil.protocols.cia301 import CONSUMER_HEARTBEAT, NMT_OPERATIONAL, PRODUCER_HEARTBEAT
from hil.protocols.cia402 import (
    DI_HOME_SWITCH,
    DI_NEGATIVE_LIMIT,
    DI_POSITIVE_LIMIT,
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

#: the numpy type of each struct code a PDO may map (integers: what the bank packs)
NUMPY_OF_STRUCT = {"b": "i1", "B": "u1", "h": "<i2", "H": "<u2", "l": "<i4", "L": "<u4",
                   "q": "<i8"}
#: the actual values the bank computes each cycle: what its TPDOs may map
ACTUAL_KEYS = (POSITION_KEY, DEMAND_POSITION_KEY, DEMAND_VELOCITY_KEY, INPUTS_KEY, VELOCITY_KEY,
               TORQUE_KEY, STATUSWORD_KEY)
MODE_KEY, TARGET_TORQUE_KEY = (MODES_DISPLAY, 0), (TARGET_TORQUE, 0)
CST = OPERATION_MODES["cst"].code
#: what the current of a CST cycle reads: rated current, max torque, trip level, then the
#: max current (0x6073; the max torque again where the dictionary lacks it, as min() takes it)
LIMIT_KEYS = ((RATED_CURRENT, 0), (MAX_TORQUE, 0), (OVERCURRENT_TRIP, 0))
MAX_CURRENT_KEY = (MAX_CURRENT, 0)
#: |counts| below this, and count offsets too, keep every sum of the actual values an integer
#: below 2**53: exact in float64, as in Python's ints
SAFE_COUNTS = SAFE_OFFSET = 2.0**51
STEADY_STATUSWORD = STATUSWORD[OPERATION_ENABLED] | SW_FOLLOWS_COMMAND  # CST's bits
DI_WEIGHTS = np.array([DI_NEGATIVE_LIMIT, DI_POSITIVE_LIMIT, DI_HOME_SWITCH], dtype=float)
#: the values each actual value takes (what a TPDO field must hold; per turn below 2**31)
ACTUAL_RANGES = {POSITION_KEY: (0, 2**31 - 1), DEMAND_POSITION_KEY: (-(2**31), 2**31 - 1),
                 DEMAND_VELOCITY_KEY: (-(2**31), 2**31 - 1), INPUTS_KEY: (0, 7),
                 VELOCITY_KEY: (-(2**31), 2**31 - 1), TORQUE_KEY: (-32768, 32767),
                 STATUSWORD_KEY: (0, 0xFFFF)}


def pdo_dtype(pdo: Pdo) -> np.dtype | None:
    """``pdo``'s data as a packed numpy record (fields ``f0``, ``f1``... in mapping order), or
    None when it maps a type the bank does not pack."""
    codes = pdo.layout.format.lstrip("<")
    if any(code not in NUMPY_OF_STRUCT for code in codes):
        return None
    formats = [np.dtype(NUMPY_OF_STRUCT[code]) for code in codes]
    offsets = [sum(each.itemsize for each in formats[:i]) for i in range(len(formats))]
    if sum(each.itemsize for each in formats) != pdo.layout.size:
        return None
    return np.dtype({"names": [f"f{i}" for i in range(len(codes))], "formats": formats,
                     "offsets": offsets, "itemsize": pdo.layout.size})


def holds(dtype: np.dtype, bounds: tuple[int, int]) -> bool:
    """Whether the integer type ``dtype`` holds every value in ``bounds``."""
    info = np.iinfo(dtype)
    return bool(info.min <= bounds[0] and bounds[1] <= info.max)


def stack_matches(plants: Sequence[AxisPlant]) -> bool:
    """Whether one stacked ``matmul`` of the plants' step matrices gives, bit for bit, each
    plant's own product (the same BLAS call on this machine), on a few random state vectors."""
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
    """What the bank packs, for the PDO maps, dispatch tables and mode motions the nodes have
    now (valid while each node's tables are the very objects it was built from)."""

    def __init__(self, nodes: Sequence[DriveNode]) -> None:
        self.tokens = [self.token_of(node) for node in nodes]
        self.ok = False
        rpdos = [self.rpdo_of(node) for node in nodes]
        if any(pdo is None for pdo in rpdos):
            return
        self.rpdos: list[Pdo] = [pdo for pdo in rpdos if pdo is not None]
        first = self.rpdos[0]
        self.rpdo_dtype = pdo_dtype(first)
        if self.rpdo_dtype is None or any(pdo.keys != first.keys or pdo.layout.format !=
                                          first.layout.format for pdo in self.rpdos):
            return
        if CONTROLWORD_KEY not in first.keys or TARGET_TORQUE_KEY not in first.keys or \
                set(first.keys) & set(ACTUAL_KEYS) or any(
                    key != CONTROLWORD_KEY and key[0] in node._write_effects
                    for node in nodes for key in first.keys):
            return  # a key whose writing means more than its value stored
        self.rpdo_cobs = [pdo.cob_id for pdo in self.rpdos]
        self.rpdo_size = first.layout.size
        self.sync_cobs = [node._sync_cob_id for node in nodes]
        fields = {key: f"f{i}" for i, key in enumerate(first.keys)}
        self.cw_field, self.torque_field = fields[CONTROLWORD_KEY], fields[TARGET_TORQUE_KEY]
        #: the RPDO's plain values (stored as they are), its controlword last
        self.stored_keys = (*(key for key in first.keys if key != CONTROLWORD_KEY),
                            CONTROLWORD_KEY)
        self.stored_fields = [fields[key] for key in self.stored_keys]
        #: the bank's table's rows: the actual values, then the RPDO's (no key in both)
        self.written_keys = (*ACTUAL_KEYS, *self.stored_keys)
        transmitters = [node.pdos._transmitters for node in nodes]
        firsts = transmitters[0]
        if any(len(each) != len(firsts) for each in transmitters):
            return
        self.tpdo_dtypes: list[np.dtype] = []
        for j, pdo in enumerate(firsts):
            dtype = pdo_dtype(pdo)
            if dtype is None or not set(pdo.keys) <= set(ACTUAL_KEYS) or not all(
                    holds(dtype[f"f{i}"], ACTUAL_RANGES[key]) for i, key in enumerate(pdo.keys)
            ) or any(
                    each[j].keys != pdo.keys or each[j].layout.format != pdo.layout.format
                    or each[j].trans_type != 1 for each in transmitters):
                return
            self.tpdo_dtypes.append(dtype)
        self.transmitters = transmitters
        self.tpdo_cobs = [[pdo.cob_id for pdo in each] for each in transmitters]
        # one record per node: every TPDO's fields, one after the other
        names, formats, offsets, rows, start = [], [], [], [], 0
        self.tpdo_pieces = []
        for j, (pdo, dtype) in enumerate(zip(firsts, self.tpdo_dtypes, strict=True)):
            for i, key in enumerate(pdo.keys):
                names.append(f"t{j}f{i}")
                formats.append(dtype[i])
                offsets.append(start + sum(dtype[k].itemsize for k in range(i)))
                rows.append(ACTUAL_KEYS.index(key))
            self.tpdo_pieces.append((start, start + dtype.itemsize))
            start += dtype.itemsize
        self.tpdo_record = np.zeros(len(nodes), np.dtype(
            {"names": names, "formats": formats, "offsets": offsets, "itemsize": start}))
        self.tpdo_fields = [self.tpdo_record[name] for name in names]
        self.tpdo_rows = rows
        #: each node's TPDO frames in the packed record: (COB-ID, first byte, end)
        self.tpdo_slices = [[(cob, i * start + begin, i * start + end) for cob, (begin, end)
                             in zip(cobs, self.tpdo_pieces, strict=True)]
                            for i, cobs in enumerate(self.tpdo_cobs)]
        # a node's TPDO heard by another node would reach it within the same transmission
        if any(other is not node and other.hears(cob)
               for node, cobs in zip(nodes, self.tpdo_cobs, strict=True) for cob in cobs
               for other in nodes):
            return
        self.limit_getters = [itemgetter(*LIMIT_KEYS, MAX_CURRENT_KEY if MAX_CURRENT_KEY in
                                         node._values else LIMIT_KEYS[1]) for node in nodes]
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
    """The steady cycle of ``nodes``, each hearing its bus's ``inboxes`` (the frames waiting
    for it), at once (:meth:`cycle`). Its arrays are preallocated, one column per node: a
    cycle is a fixed number of numpy calls on them, whatever the number of nodes."""

    def __init__(self, nodes: Sequence[DriveNode], inboxes: Sequence[deque[Frame]]) -> None:
        self.nodes, self.inboxes = list(nodes), list(inboxes)
        plants = [node.plant for node in nodes]
        self.plants = plants
        count, n = len(plants), plants[0]._n
        self.n = n
        self.matrices = np.stack([plant._step_matrix for plant in plants])
        # the plants' two buffers, as rows of the bank's: each plant swaps its own each step
        self.buffers = (np.zeros((count, n + 1)), np.zeros((count, n + 1)))
        self.rows = tuple([buffer[i] for i in range(count)] for buffer in self.buffers)
        self.columns = tuple(buffer[:, :, None] for buffer in self.buffers)
        self.phase = 0  # the buffer holding each plant's state now
        self.u_offset = np.array([plant.axis.u_offset for plant in plants], dtype=float)
        self.y_offset = np.array([plant.axis.y_offset for plant in plants], dtype=float)
        self.dt = np.array([plant.dt for plant in plants])
        per_turn = np.array([plant.increments_per_rev for plant in plants], dtype=float)
        self.per_turn = per_turn
        self.to_counts = np.stack((np.full(count, 360.0), np.full(count, 360.0))), \
            np.stack((per_turn, per_turn))  # [deg] / 360.0 * per turn, as the node's
        self.amplifier = np.array([plant.current_limit_ma for plant in plants])
        # the switches as "at or above" thresholds of (-position, position, position)
        switches = [node._switches for node in nodes]
        self.thresholds = np.array([[-each.negative_limit_deg, each.positive_limit_deg,
                                     each.home_switch_deg] for each in switches]).T.copy()
        self.switch_signs = np.repeat([[-1.0], [1.0], [1.0]], count, axis=1)
        self.ones = np.ones((3, count))
        self.hits = np.zeros((3, count))
        self.wrap = np.full((2, count), 2.0**31), np.full((2, count), 2.0**32)
        self.safe_counts = np.full((2, count), SAFE_COUNTS)
        # the velocity's INTEGER32 and the torque's INTEGER16 bounds
        self.clamp = (np.stack((np.full(count, -(2.0**31)), np.full(count, -32768.0))),
                      np.stack((np.full(count, 2.0**31 - 1), np.full(count, 32767.0))))
        self.thousand = np.full(count, 1000.0)
        self.steady_word = np.full(count, float(STEADY_STATUSWORD))
        self.limited_word = np.full(count, float(STEADY_STATUSWORD | SW_INTERNAL_LIMIT))
        self.moved = np.zeros((2, count))   # position [deg], velocity [deg/s]
        self.position, self.velocity = self.moved
        self.counts = np.zeros((2, count))  # the same [increments], [increments/s]
        self.size, self.safe = np.zeros((2, count)), np.zeros((2, count), dtype=bool)
        self.wanted, self.limited, self.scratch = np.zeros(count), np.zeros(count), \
            np.zeros(count)
        self.flags, self.active = np.zeros(count, dtype=bool), np.zeros(count, dtype=bool)
        # the last entry of each plant's buffer: the input it takes, the output it gives
        self.ends = tuple(buffer[:, n] for buffer in self.buffers)
        #: what each node's values take this cycle, a row per key: the actual values
        #: (ACTUAL_KEYS), then the RPDO's (the layout's), as floats (integers below 2**53)
        self.table = np.zeros((len(ACTUAL_KEYS), count))
        self.table_rows = list(self.table)
        self.layout: BankLayout | None = None
        self.limits: list[tuple[int, int, int, int]] = []
        self.rated = self.trip = self.limit = self.least = np.zeros(count)
        self.steady_controlwords: dict[int, bool] = {}

    @staticmethod
    def of(nodes: Sequence[DriveNode], inboxes: Sequence[deque[Frame]]) -> DriveBank | None:
        """A bank of ``nodes``, or None when their plants cannot be stepped as one exactly."""
        plants = [node.plant for node in nodes]
        if len({plant._n for plant in plants}) != 1 or len({id(p) for p in plants}) != \
                len(plants) or not stack_matches(plants):
            return None
        return DriveBank(nodes, inboxes)

    def cycle(self, heard_ns: int | None) -> bool:
        """Each node's waiting frames as one steady cycle, when they and the nodes are in the
        steady state (then the frames are taken, and True); else False, nothing changed."""
        layout = self.layout
        if layout is None or not layout.current(self.nodes):
            layout = self._relayout()
        if not layout.ok:
            return False
        data = self._rpdo_data(layout)
        if data is None:
            return False
        received = np.frombuffer(b"".join(data), layout.rpdo_dtype)
        steady = self._steady(layout, received[layout.cw_field].tolist())
        if steady is None:
            return False
        offsets, positions, now = steady
        # the current (MotorLoops.current, CyclicTorque.current): int16 * rated is exact in
        # float64, as the node's int product
        wanted, limited, scratch = self.wanted, self.limited, self.scratch
        np.multiply(received[layout.torque_field], self.rated, out=wanted)
        np.divide(wanted, self.thousand, out=wanted)
        np.abs(wanted, out=scratch)
        if True in np.greater(scratch, self.trip, out=self.flags).tolist():
            return False  # the over-current fault
        # max(wanted, -limit) then min(.., limit): with limit > 0 no tie of zeros, where
        # numpy's and Python's picks differ
        np.maximum(wanted, self.least, out=limited)
        np.minimum(limited, self.limit, out=limited)
        # the plant (AxisPlant.step, one period); |limited| <= limit <= the amplifier's limit,
        # so the plant's own saturation leaves it as it is
        phase = self.phase
        np.subtract(limited, self.u_offset, out=self.ends[phase])
        np.matmul(self.matrices, self.columns[phase], out=self.columns[1 - phase])
        moved, counts, position = self.moved, self.counts, self.position
        np.add(self.ends[1 - phase], self.y_offset, out=position)
        np.subtract(position, positions, out=self.velocity)
        np.divide(self.velocity, self.dt, out=self.velocity)
        np.divide(moved, self.to_counts[0], out=counts)
        np.multiply(counts, self.to_counts[1], out=counts)
        np.abs(counts, out=self.size)
        if False in np.less(self.size, self.safe_counts, out=self.safe).ravel().tolist():
            return False  # not finite, or too large to count exactly: the node's own path
        self._actuals(layout, offsets, received)
        self._commit(layout, heard_ns, now)
        return True

    def _relayout(self) -> BankLayout:
        """The layout of the nodes' tables now, and the bank's table to fit it."""
        layout = self.layout = BankLayout(self.nodes)
        if layout.ok:  # a row per value the RPDO stores too
            self.table = np.zeros((len(layout.written_keys), len(self.nodes)))
            self.table_rows = list(self.table)
        return layout

    def _actuals(self, layout: BankLayout, offsets: list[int], received: np.ndarray) -> None:
        """The table's rows: the actual values (DriveNode._refresh_actuals) in ACTUAL_KEYS
        order, then the RPDO's values; integers held exactly as floats."""
        table, counts = self.table, self.counts
        position, demand, demand_speed, inputs, speed, torque, word, *stored = self.table_rows
        if any(offsets):  # homed: the count's offset, added as the node adds it
            offset = np.array(offsets, dtype=float)
            np.floor(counts[0], out=position)
            np.add(position, offset, out=position)
            np.add(counts[0], offset, out=demand)
            np.floor(demand, out=demand)
        else:
            np.floor(counts[0], out=demand)
            position[...] = demand
        np.remainder(position, self.per_turn, out=position)
        np.rint(counts[1], out=speed)
        demand_speed[...] = speed
        wrapped = table[1:3]  # the demand position and velocity, wrapped into INTEGER32
        shift, modulus = self.wrap
        np.add(wrapped, shift, out=wrapped)
        np.remainder(wrapped, modulus, out=wrapped)
        np.subtract(wrapped, shift, out=wrapped)
        np.multiply(self.limited, self.thousand, out=torque)
        np.divide(torque, self.rated, out=torque)
        np.rint(torque, out=torque)
        clamped = table[4:6]  # the velocity into INTEGER32, the torque into INTEGER16
        np.maximum(clamped, self.clamp[0], out=clamped)
        np.minimum(clamped, self.clamp[1], out=clamped)
        # the switches: (-position, position, position) less their thresholds, at or above 0
        hits = self.hits
        hits[...] = self.position
        np.multiply(hits, self.switch_signs, out=hits)
        np.subtract(hits, self.thresholds, out=hits)
        np.heaviside(hits, self.ones, out=hits)
        np.dot(DI_WEIGHTS, hits, out=inputs)
        word[...] = self.steady_word
        np.copyto(word, self.limited_word, where=np.not_equal(self.limited, self.wanted,
                                                              out=self.active))
        for row, field in zip(stored, layout.stored_fields, strict=True):
            row[...] = received[field]

    def _rpdo_data(self, layout: BankLayout) -> list[bytes] | None:
        """Each node's RPDO data, when each has exactly its RPDO and a SYNC waiting."""
        data = []
        size = layout.rpdo_size
        for inbox, rpdo_cob, sync_cob in zip(self.inboxes, layout.rpdo_cobs, layout.sync_cobs,
                                             strict=True):
            if len(inbox) != 2:
                return None
            (first_id, first), (second_id, second) = inbox
            if first_id != rpdo_cob or len(first) != size or second_id != sync_cob or second:
                return None
            data.append(first)
        return data

    def _steady(self, layout: BankLayout, controlwords: list[int]
                ) -> tuple[list[int], list[float], list[int]] | None:
        """Each node's count offset, plant position and time after this cycle, when every
        node is in the steady state with nothing due this cycle (else None); the limits
        updated, the plants' buffers the bank's."""
        offsets, positions, now, limits = [], [], [], []
        steady_controlwords = self.steady_controlwords
        if self.plants[0]._xu is self.rows[1 - self.phase][0]:
            self.phase = 1 - self.phase  # the plants stepped on their own since
        adopted = True
        for node, cw, getter, row in zip(self.nodes, controlwords, layout.limit_getters,
                                         self.rows[self.phase], strict=True):
            states, plant, values = node.states, node.plant, node._values
            if node.nmt_state != NMT_OPERATIONAL or states.state != OPERATION_ENABLED or \
                    node._fault_list or node._delayed or node.pdos.pending or \
                    states.comm_warning or states.ramp_start_ns is not None or \
                    cw != states.controlword or not (steady_controlwords.get(cw) or
                                                     self._steady_controlword(cw)) or \
                    node._gone_after_ns or not node._sync_timebase or \
                    node._steps_per_sync != 1 or plant._configured_load or \
                    plant.extra_disturbance_ma or values[MODE_KEY] != CST:
                return None
            t = node._sync_origin_ns + node._sync_time_ns + node._plant_period_ns
            period_ms = values[(PRODUCER_HEARTBEAT, 0)]
            if period_ms and (node._hb_next_ns is None or t >= node._hb_next_ns):
                return None  # a heartbeat due
            if node._hb_consumer_armed and t - node._hb_last_ns > \
                    (values[(CONSUMER_HEARTBEAT, 1)] & 0xFFFF) * 1_000_000:
                return None  # the master's heartbeat lost
            limits.append(getter(values))
            offsets.append(node.motor.count.offset)
            positions.append(plant.position_deg)
            now.append(t)
            adopted = adopted and plant._xu is row
        if limits != self.limits and not self._set_limits(limits):
            return None
        if any(offsets) and max(map(abs, offsets)) >= SAFE_OFFSET:
            return None
        if not adopted:
            self._adopt()
        return offsets, positions, now

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

    def _set_limits(self, limits: list[tuple[int, int, int, int]]) -> bool:
        """The nodes' rated current, trip level and current limit (MotorLoops'
        ``current_limit_ma``) from their objects; False (the nodes' own path) when a rated
        current or a limit is not > 0, or too large to multiply exactly as floats."""
        table = np.array(limits, dtype=np.int64)
        if table.min() <= 0 or table[:, 0].max() >= 2**37:
            return False
        rated, max_torque, trip, max_current = table.T
        # min() of ints, and of a current > 0 and the amplifier's limit > 0
        limit = np.minimum(np.minimum(max_torque, max_current) * rated / 1000.0, self.amplifier)
        if not (limit > 0).all():
            return False
        self.limits = limits
        self.rated, self.trip = rated.astype(float), trip.astype(float)
        self.limit, self.least = limit, -limit
        return True

    def _adopt(self) -> None:
        """Each plant's buffers made rows of the bank's (their values as they are)."""
        first, second = self.buffers
        for i, plant in enumerate(self.plants):
            state, spare = plant._xu.copy(), plant._next.copy()
            first[i], second[i] = state, spare
            plant._xu, plant._next = self.rows[0][i], self.rows[1][i]
        self.phase = 0

    def _commit(self, layout: BankLayout, heard_ns: int | None, now: list[int]) -> None:
        """Each node left as its own cycle leaves it, its TPDOs sent."""
        moved = self.moved.tolist()
        for inbox in self.inboxes:
            inbox.clear()
        phase = self.phase
        self.phase = 1 - phase
        heard = time.monotonic_ns() if heard_ns is None else heard_ns
        keys = layout.written_keys
        table = self.table.astype(np.int64)
        raw = self._packed_tpdos(layout, table)
        for (node, plant, rpdo, transmitters, t, row, active, current, position, velocity,
             row_out, row_in, slices) in zip(
                self.nodes, self.plants, layout.rpdos, layout.transmitters, now,
                table.T.tolist(), self.active.tolist(), self.limited.tolist(), moved[0],
                moved[1], self.rows[1 - phase], self.rows[phase], layout.tpdo_slices,
                strict=True):
            node._heard_ns = heard
            rpdo.length_error = False
            node._values.update(zip(keys, row, strict=True))
            node.states.limit_active = active
            plant.applied_current_ma = current
            plant.velocity_deg_s, plant.position_deg = velocity, position
            plant.steps += 1
            plant._xu, plant._next = row_out, row_in
            node.sync_count += 1
            node._sync_time_ns += node._plant_period_ns
            node._sync_last_ns = t
            node._sync_armed = True
            for pdo in transmitters:
                pdo.counter = 0
            node._serviced = True
            if slices:
                node._send([(cob, raw[begin:end]) for cob, begin, end in slices])

    @staticmethod
    def _packed_tpdos(layout: BankLayout, table: np.ndarray) -> bytes:
        """Every node's TPDO data, packed from the table's actual values: a record per node
        with each TPDO's fields (the layout's slices cut each node's frames out of it)."""
        record = layout.tpdo_record
        for field, row in zip(layout.tpdo_fields, layout.tpdo_rows, strict=True):
            field[...] = table[row]
        return record.tobytes()
