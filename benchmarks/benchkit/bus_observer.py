"""A second client of a socketcand server, in a process of its own: every frame of the bus
with the server's time stamp (``< frame ID SECS.USECS DATA >``), printed as JSON
(``[[id, stamp], ...]``) once the server closes the connection.

The drive emulator's server stamps a frame it forwards from the master when it takes the
command (after its wake-up), and one of its own when it sends it: the two hops of a cycle on
the emulator's side. ``python bus_observer.py HOST PORT``; its first line, ``ready``, says it
is in raw mode.
"""

from __future__ import annotations

import json
import sys

import can

from hil.drivers.socketcand_bus import SocketcandBus


def main() -> int:
    host, port = sys.argv[1], int(sys.argv[2])
    bus = SocketcandBus("can0", host, port)
    print("ready", flush=True)
    frames: list[tuple[int, float]] = []
    try:
        while True:
            msg = bus.recv(1.0)
            if msg is not None:
                frames.append((msg.arbitration_id, msg.timestamp))
    except can.CanOperationError:  # the server is gone: the run is over
        pass
    finally:
        bus.shutdown()
    json.dump(frames, sys.stdout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
