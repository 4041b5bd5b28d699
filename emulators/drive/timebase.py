"""What an emulated drive's time follows (``hil emulate drive --clock``):

* ``auto`` - its own wall clock, until a lockstep master asks for its time by writing
  :data:`TIME_BASE` = N > 0 (then the SYNCs' time, given up after N ms of wall time without a
  frame, or when the master writes 0 or resets the node);
* ``sync`` - the SYNCs' time from power-on: time passes only when SYNCs come;
* ``wall`` - its own clock always: a master that asks is refused (SDO abort), so it knows.
"""

CLOCKS = ("auto", "sync", "wall")
#: the manufacturer object a lockstep master writes: 0 the drive's own clock, N > 0 the
#: master's SYNC time, with a bound of N ms of wall time without a frame (UNSIGNED32)
TIME_BASE = 0x2005
