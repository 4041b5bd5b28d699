"""hil's bench emulator on the wire: how a lockstep master tells it from a real bench, and how
it gives the emulator its time. Tables only, read by both sides: the master
(:mod:`hil.drivers.bench.emulator_clock`) and the emulator (:mod:`hil.emulators.bench.timekeeper`).

* Identification: Modbus "Read Device Identification" (FC 0x2B, MEI type 0x0E, the basic
  objects) of the relay module's unit. hil's emulator answers VendorName ``hil`` and
  ProductCode ``hil-bench-emulator``; a real module answers with its own, or with exception 1.
* The clock: unit :data:`CLOCK_UNIT` (248), the first of the ids Modbus reserves (248-255):
  ``[units]`` takes 1-247 only, so no bench map can name it, and no device on a real line
  answers it. Its holding registers:

  ======== ========= =================================================================
  register function  meaning
  ======== ========= =================================================================
  0-3      FC16      ``TIME``: the master's time, ns since its first tick (uint64, high
                     word first); the plant steps until it is there, then the answer
  0-3      FC03      the plant's time, ns
  4        FC06      ``CONTROL`` = N > 0: a lockstep session starts: the plant and its fault
                     schedule start again from t = 0 and follow this master, whose request
                     timeout is N ms; 0: the master lets go
  4        FC03      the emulator's clock: 0 its wall clock, 1 a master's time, 2 waiting
                     for a master
  ======== ========= =================================================================

  Exception 1 (illegal function): the emulator keeps its wall clock (``--clock wall``);
  6 (busy): another master holds its time; 3 (illegal value): a ``TIME`` more than a minute
  ahead of the plant (a master asks for one tick at a time).
"""

from __future__ import annotations

VENDOR = "hil"
PRODUCT_CODE = "hil-bench-emulator"
PRODUCT_NAME = "hil relay bench emulator"
REVISION = "1.0"        # of this protocol
CLOCK_UNIT = 248
TIME_REGISTER = 0       # 4 registers: ns, uint64, high word first
CONTROL_REGISTER = 4    # write: the master's request timeout in ms (start) or 0 (let go)
CLOCK_REGISTERS = 5
#: what an emulator's plant time follows (``hil emulate bench --clock``): ``auto`` (its wall
#: clock, until a lockstep master takes it), ``wall`` (always), ``master`` (waits for one)
CLOCKS = ("auto", "wall", "master")
#: what CONTROL reads
ON_WALL_CLOCK, ON_MASTER_TIME, WAITING_FOR_MASTER = 0, 1, 2
#: the exceptions the clock answers
KEEPS_WALL_CLOCK, HELD_BY_ANOTHER = 0x01, 0x06


def time_words(t_ns: int) -> list[int]:
    """``t_ns`` as the four registers of ``TIME``."""
    return [(t_ns >> shift) & 0xFFFF for shift in (48, 32, 16, 0)]


def time_of(words: list[int]) -> int:
    """The ns of the four registers of ``TIME``."""
    return (words[0] << 48) | (words[1] << 32) | (words[2] << 16) | words[3]
