"""The bank of a lockstep bus's drives (:mod:`hil.emulators.drive.bank`) against each node's own
path: one scripted sequence through both, every frame and every node's state compared after
each transmission, bit for bit."""

import math
import re
import socket
import struct
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from hil.emulation import serve_drives
from hil.emulators.drive import bank as bank_module
from hil.emulators.drive.bank import DriveBank, stack_matches
from hil.emulators.drive.config import DriveEmulatorConfig
from hil.emulators.drive.plant import AxisPlant
from hil.emulators.drive.runners import LockstepDrive, deliver
from hil.emulators.drive.switches import Switches

IDS = (1, 2, 3)
CST, ENABLE, FAULT_RESET, QUICK_STOP = 10, 0x0F, 0x80, 0x02
MASTER_HEARTBEAT = 0x77F
# a rated current that makes the torque's per mille a fraction to round; switches within the
# axes' travel
CONFIG = DriveEmulatorConfig(rated_current_ma=1300, max_torque_permille=900,
                             switches=Switches(negative_limit_deg=-0.5, positive_limit_deg=2.0,
                                               home_switch_deg=1.0))


def exact(value: Any) -> Any:
    """``value`` with every float as its bits (-0.0 is not 0.0), containers alike."""
    if isinstance(value, float):
        return ("float", value.hex() if math.isfinite(value) else repr(value),
                math.copysign(1.0, value))
    if isinstance(value, dict):
        return {key: exact(each) for key, each in value.items()}
    if isinstance(value, (list, tuple)):
        return [exact(each) for each in value]
    if isinstance(value, np.ndarray):
        return exact(value.tolist())
    return value


def snapshot(drive: LockstepDrive) -> list[dict[str, Any]]:
    """What each node holds, but the wall clock's time of its last frame."""
    nodes = []
    for node in drive.nodes:
        states, plant, pdos = node.states, node.plant, node.pdos
        nodes.append(exact({
            "values": dict(node._values), "nmt": node.nmt_state, "state": states.state,
            "controlword": states.controlword, "limit": states.limit_active,
            "ramp": states.ramp_start_ns, "warning": states.comm_warning,
            "plant": [plant.position_deg, plant.velocity_deg_s, plant.applied_current_ma,
                      plant.steps, plant._xu, plant._next],
            "offset": node.motor.count.offset, "syncs": node.sync_count,
            "times": [node._sync_time_ns, node._sync_last_ns, node._sync_armed,
                      node._hb_next_ns, node._hb_last_ns, node._hb_consumer_armed],
            "pdos": [(pdo.counter, pdo.length_error, pdo.last_data) for pdo in pdos.pdos],
            "pending": dict(pdos.pending), "errors": node.internal_errors,
            "serviced": node._serviced, "events": list(node.faults.events),
        }))
    return nodes


class Rig:
    """A raw master on a 3-drive lockstep bus: each transmission's answers and the nodes'
    state after it, recorded."""

    def __init__(self, bank: bool) -> None:
        self.drive: Any = LockstepDrive(CONFIG, node_ids=IDS, bank=bank)
        self.bus = self.drive.master_bus
        self.bank = self.drive._bank
        self.count(self.bank)
        self.log: list[Any] = []

    def close(self) -> None:
        self.drive.close()

    def count(self, bank: DriveBank | None) -> None:
        """Count the transmissions ``bank`` runs."""
        self.banked = self.mixed = 0  # transmissions the bank ran, with some nodes' own path
        if bank is not None:
            cycle = bank.cycle

            def counted(heard_ns: int | None, own: Callable[[int], None]) -> bool:
                owned = []

                def told(i: int) -> None:
                    owned.append(i)
                    own(i)
                done = cycle(heard_ns, told)
                self.banked += done
                self.mixed += done and bool(owned)
                return done
            bank.cycle = counted  # type: ignore[method-assign]

    def send(self, frames: list[tuple[int, bytes]]) -> None:
        self.bus.send_frames(frames)
        answers = []
        while (frame := self.bus.recv_frame()) is not None:
            answers.append(frame)
        self.log.append((frames, answers, snapshot(self.drive)))

    def cycle(self, controlwords: dict[int, int], torques: dict[int, int],
              extra: tuple[tuple[int, bytes], ...] = ()) -> None:
        """Each node's RPDO (controlword, target torque), then the SYNC, in one send."""
        self.send([*extra, *((0x200 + node, struct.pack("<Hh", controlwords[node],
                                                        torques[node])) for node in IDS
                             if node in torques), (0x080, b"")])

    def sdo_write(self, node: int, index: int, sub: int, value: int, size: int) -> None:
        command = 0x23 | ((4 - size) << 2)
        self.send([(0x600 + node, struct.pack("<BHBl" if value < 0 else "<BHBL", command,
                                              index, sub, value))])

    def sdo_read(self, node: int, index: int, sub: int = 0) -> None:
        self.send([(0x600 + node, struct.pack("<BHB", 0x40, index, sub) + bytes(4))])


class WireRig(Rig):
    """The same raw master over socketcand on loopback, the drives served as ``hil emulate
    drive`` serves them (on SYNC time): each transmission one TCP write, its answers those
    before the echo that follows it."""

    def __init__(self, bank: bool) -> None:
        config = replace(CONFIG, object_values=(((0x1018, 4), 1234),))  # not a random serial
        self.drive = serve_drives(config, list(IDS), "127.0.0.1", 0, clock="sync", bank=bank)
        # the time service on the frames alone: its wall-clock ticks would land between the
        # script's transmissions at random (what they do is the same on both paths)
        self.drive.server.on_tick = None
        self.drive.server.start()
        self.sock = socket.create_connection(self.drive.server.address, timeout=5.0)
        self.replies = b""
        self.sock.sendall(b"< open can0 >< rawmode >")
        self.read_until(b"< ok >< ok >")
        self.bank = self.drive.bank
        self.count(self.bank)
        self.log = []

    def read_until(self, mark: bytes) -> bytes:
        """What the server sent before ``mark`` (read up to and including it)."""
        while mark not in self.replies:
            self.replies += self.sock.recv(65536)
        before, _, self.replies = self.replies.partition(mark)
        return before

    def send(self, frames: list[tuple[int, bytes]]) -> None:
        self.sock.sendall(b"".join(b"< send %03X %d %s >" % (can_id, len(data), " ".join(
            f"{byte:02X}" for byte in data).encode()) for can_id, data in frames))
        self.sock.sendall(b"< echo >")
        answers = [(int(can_id, 16), bytes.fromhex(data.decode())) for can_id, data in
                   re.findall(rb"< frame ([0-9A-Fa-f]+) [0-9.]+ ([0-9A-Fa-f]*) >",
                              self.read_until(b"< echo >"))]
        self.log.append((frames, answers, snapshot(self.drive)))

    def close(self) -> None:
        self.sock.close()
        self.drive.stop()


def script(rig: Rig) -> None:
    """Enable three CST drives, run them (current limit reached, a homed count, heartbeats
    both ways and from node to node, a cycle without one RPDO), fault one by over-current
    mid-run and reset it, read actual values by SDO, quick-stop one, and run on."""
    rig.send([(0x000, bytes([0x01, 0]))])  # NMT start all
    for node in IDS:
        rig.sdo_write(node, 0x6060, 0, CST, 1)
    rig.sdo_write(2, 0x1017, 0, 7, 2)  # node 2 produces a heartbeat every 7 ms
    rig.sdo_write(1, 0x1016, 1, (0x7F << 16) | 40, 4)  # node 1 watches the master: 40 ms
    # node 3 watches node 2: node 2's heartbeat reaches it within the transmission
    rig.sdo_write(3, 0x1016, 1, (2 << 16) | 40, 4)
    cws = dict.fromkeys(IDS, 0x06)
    zero = dict.fromkeys(IDS, 0)
    for cw in (0x06, 0x07, ENABLE):
        cws = dict.fromkeys(IDS, cw)
        rig.cycle(cws, zero)
    for k in range(420):
        torques = {node: round(1400 * math.sin(k / (9.0 + node))) for node in IDS}
        extra: tuple[tuple[int, bytes], ...] = ()
        if k % 30 == 0:
            extra = ((MASTER_HEARTBEAT, bytes([0x05])),)
        if k == 60:
            rig.drive.nodes[1].motor.count.offset = 3_000_000_123  # homed: a demand past 2**31
        if k == 100:
            torques[2] = 12_000  # 15.6 A: over the 15 A trip level
        if k in (170, 171, 172, 173):  # the fault reaction over: reset, enable again
            cws[2] = (FAULT_RESET, 0x06, 0x07, ENABLE)[k - 170]
        if k == 200:
            cws[3] = QUICK_STOP
        if k in (260, 261, 262):
            cws[3] = (0x06, 0x07, ENABLE)[k - 260]
        if k == 300:
            torques.pop(1)  # a cycle without node 1's RPDO
        if k in (320, 330):  # node 3 stopped (its plant not stepped), started again
            extra = ((0x000, bytes([0x02 if k == 320 else 0x01, 3])),)
        if k in (400, 401, 402, 403):  # its fault (the communication lost) reset
            cws[3] = (FAULT_RESET, 0x06, 0x07, ENABLE)[k - 400]
        rig.cycle(cws, torques, extra)
        if k in (50, 150, 250, 350):
            for node in IDS:
                for index in (0x6064, 0x606C, 0x6077, 0x6041):
                    rig.sdo_read(node, index)


@pytest.mark.parametrize("stacked", [False, True])
def test_the_bank_leaves_every_frame_and_state_as_each_nodes_own_path(stacked, monkeypatch):
    """Every frame and state equal, with the plants stepped by their own products and by
    one stacked product."""
    monkeypatch.setattr(bank_module, "STACK_FROM_NODES", 1 if stacked else 99)
    own, bank = Rig(bank=False), Rig(bank=True)
    check_the_same(own, bank, stacked)
    own.close()
    bank.close()


@pytest.mark.parametrize("stacked", [False, True])
def test_drives_served_over_socketcand_run_as_a_bank_too(stacked, monkeypatch):
    """``hil emulate drive``'s drives (each read's frames handed over together) leave every
    answer and state as each node's own path does over the same wire."""
    monkeypatch.setattr(bank_module, "STACK_FROM_NODES", 1 if stacked else 99)
    own, bank = WireRig(bank=False), WireRig(bank=True)
    try:
        check_the_same(own, bank, stacked)
    finally:
        own.close()
        bank.close()


def check_the_same(own: Rig, bank: Rig, stacked: bool) -> None:
    """The script through both rigs: the same answers and states, most cycles banked."""
    assert own.bank is None and bank.bank is not None and bank.bank.stacked is stacked
    script(own)
    script(bank)
    assert bank.banked > 200  # most cycles ran as a bank
    assert bank.mixed > 20  # some with a node on its own path (a fault, a quick stop...)
    assert len(own.log) == len(bank.log)
    for step, (a, b) in enumerate(zip(own.log, bank.log, strict=True)):
        assert a[0] == b[0], step
        assert a[1] == b[1], f"frames differ after transmission {step}: {a[0]}"
        assert a[2] == b[2], f"state differs after transmission {step}: {a[0]}"
    states = [snapshot["state"] for snapshot in own.log[-1][2]]
    assert states == ["OPERATION ENABLED"] * 3
    emcy = [answer for _, answers, _ in own.log for answer in answers if answer[0] == 0x82]
    assert emcy[0][1][:2] == struct.pack("<H", 0x2310)  # the over-current fault happened


@pytest.mark.parametrize("node_ids", [None, [5]])
def test_one_drive_runs_as_a_bank_too(node_ids):
    """A lone drive: the same answers to a steady CST run with and without the bank."""
    answers = []
    for bank in (False, True):
        drive = LockstepDrive(node_ids=node_ids, bank=bank)
        node = drive.node.node_id
        bus = drive.master_bus
        sdo = struct.pack("<BHBB", 0x2F, 0x6060, 0, CST) + bytes(3)
        frames: list[Any] = []
        for data in ([(0x000, bytes([0x01, 0]))], [(0x600 + node, sdo)],
                     *([(0x200 + node, struct.pack("<Hh", cw, 0)), (0x080, b"")]
                       for cw in (0x06, 0x07, ENABLE)),
                     *([(0x200 + node, struct.pack("<Hh", ENABLE, 300 - 3 * k)), (0x080, b"")]
                       for k in range(200))):
            bus.send_frames(data)
            while (frame := bus.recv_frame()) is not None:
                frames.append(frame)
        answers.append((frames, snapshot(drive)))
        drive.close()
    assert answers[0] == answers[1]


def test_the_plants_stacked_product_is_each_plants_own():
    """One matmul over the stack gives each plant's own matrix-vector product, bit for bit
    (the bank is built only where it does)."""
    plants = [AxisPlant() for _ in range(4)]
    assert stack_matches(plants)


def test_drives_run_as_a_bank_by_default_stacked_from_four():
    drives = LockstepDrive(), LockstepDrive(node_ids=[1, 2, 3]), \
        LockstepDrive(node_ids=[1, 2, 3, 4]), LockstepDrive(node_ids=[1, 2], bank=False)
    banks = [drive._bank for drive in drives]
    assert [isinstance(bank, DriveBank) for bank in banks] == [True, True, True, False]
    assert [bank.stacked for bank in banks[:3] if bank is not None] == [False, False, True]
    for drive in drives:
        drive.close()


@pytest.mark.parametrize("bank", [False, True])
def test_a_master_silent_past_its_bound_is_gone_for_a_banked_drive_too(bank):
    """A transmission heard longer after the last one than the master's bound (0x2005 on a
    drive of its own clock) ends the master's time on both paths: the drives fault (the
    transmission dated 10 s back, for a bound of 5 s)."""
    rig = Rig(bank=bank)
    rig.send([(0x000, bytes([0x01, 0]))])
    for node in IDS:
        rig.sdo_write(node, 0x6060, 0, CST, 1)
    torques = dict.fromkeys(IDS, 100)
    for cw in (0x06, 0x07, *[ENABLE] * 10):
        rig.cycle(dict.fromkeys(IDS, cw), torques)
    for node in rig.drive.nodes:
        # as a master's 0x2005 = 5000 sets it: a bound no stall of a busy test machine reaches
        node._gone_after_ns = 5_000_000_000
    rig.cycle(dict.fromkeys(IDS, ENABLE), torques)
    assert [node.state for node in rig.drive.nodes] == ["OPERATION ENABLED"] * 3
    assert rig.banked >= 10 * bank  # the steady cycles ran in the bank's pass
    for node, inbox in zip(IDS, rig.drive._inboxes, strict=True):
        inbox.extend([(0x200 + node, struct.pack("<Hh", ENABLE, 100)), (0x080, b"")])
    deliver(rig.drive.nodes, rig.drive._inboxes, rig.bank, time.monotonic_ns() - 10_000_000_000,
            service=True)
    assert [node.state for node in rig.drive.nodes] == ["FAULT REACTION ACTIVE"] * 3
    rig.close()
