"""hil's bench emulator on the wire: how a lockstep master tells it from a real bench, and how
it gives the emulator its time. Tables only, read by both sides: the master
(:mod:`hil.drivers.bench.emulator_clock`) and the emulator (:mod:`hil.emulators.bench.timekeeper`).

* Identification: Modbus "Read Device Identification" (FC 0x2B, MEI type 0x0E, the basic
  objects) of the relay module's unit. hil's emulator answers VendorName ``hil``,
  ProductCode ``hil-bench-emulator`` and MajorMinorRevision :data:`REVISION`, the revision
  of this protocol (a master follows an emulator of its own major revision only); a real
  module answers with its own, or with exception 1.
* The clock: unit :data:`CLOCK_UNIT` (248), the first of the ids Modbus reserves (248-255):
  ``[units]`` takes 1-247 only, so no bench map can name it, and no device on a real line
  answers it. Its holding registers:

  ======== ========= =================================================================
  register function  meaning
  ======== ========= =================================================================
  0-3      FC03      ``TIME``: the plant's time, ns (uint64, high word first)
  4        FC06      ``CONTROL`` = N > 0: a lockstep session starts: the plant and its fault
                     schedule start again from t = 0 and follow this master, whose request
                     timeout is N ms; 0: the master lets go
  4        FC03      the emulator's clock: 0 its wall clock, 1 a master's time, 2 waiting
                     for a master
  5-9      FC23      ``STEP``: a numbered time request: write 5 registers at 5 (the request's
                     number 1-65535, then the master's time, ns since its first tick, uint64
                     high word first) and read 5 at 5: the plant steps until it is there,
                     then answers the number and its time. The same number again is a retry:
                     answered as the first time, without a step. So a step asked twice is
                     taken once, and its answer tells which request it answers (RTU frames
                     carry no transaction id)
  5-9      FC03      the number and the plant time of the last step
  ======== ========= =================================================================

  Exception 1 (illegal function): the emulator keeps its wall clock (``--clock wall``);
  6 (busy): another master holds its time; 3 (illegal value): a ``TIME`` more than a minute
  ahead of the plant (a master asks for one tick at a time).
"""

from __future__ import annotations

VENDOR = "hil"
PRODUCT_CODE = "hil-bench-emulator"
PRODUCT_NAME = "hil relay bench emulator"
REVISION = "2.0"        # of this protocol: 2, numbered time requests (1: FC16 TIME writes)
CLOCK_UNIT = 248
TIME_REGISTER = 0       # 4 registers: ns, uint64, high word first
CONTROL_REGISTER = 4    # write: the master's request timeout in ms (start) or 0 (let go)
STEP_REGISTER = 5       # 5 registers: the request's number, then ns (uint64, high word first)
STEP_REGISTERS = 5
CLOCK_REGISTERS = STEP_REGISTER + STEP_REGISTERS
#: the numbers of time requests: 1..MAX_NUMBER, then 1 again (0 is no request)
MAX_NUMBER = 0xFFFF
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


def step_words(number: int, t_ns: int) -> list[int]:
    """A numbered time request (or its answer) as the five registers of ``STEP``."""
    return [number, *time_words(t_ns)]


def next_number(number: int) -> int:
    """The number of the time request after ``number`` (1..MAX_NUMBER, round again)."""
    return number % MAX_NUMBER + 1


def same_major_revision(revision: str) -> bool:
    """Whether an emulator of this protocol ``revision`` speaks this master's protocol."""
    return revision.split(".")[0] == REVISION.split(".")[0]
