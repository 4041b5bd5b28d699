"""The master inside the fixed-rate loop: Ctrl-C on a real-time 2 kHz run stops the axis with a
quick stop, then disables the drive (the safe-stop path on every exit)."""

import signal

import pytest

pytestmark = [pytest.mark.timeout(60), pytest.mark.slow, pytest.mark.realtime]

CHILD = """
import struct
from hil.servo.rig import open_drive
from hil.core.clock import RealtimeClock
from hil.core.loop import FixedRateLoop, FunctionTask

master = open_drive("emulated")
master.start()
observer = master.emulator.attach_bus()
loop = FixedRateLoop(RealtimeClock(), 0.0005)
loop.add_component(master)
loop.add_task(FunctionTask("drive", write=lambda t: master.exchange(300.0)))


def moving(_t):
    if not moving.said and abs(master.emulator.node.plant.velocity_deg_s) > 300.0:
        moving.said = print("moving", flush=True) or True


moving.said = False
loop.add_task(FunctionTask("moving", write=moving))
loop.run(duration_s=60)
words = []
while (msg := observer.recv(0)) is not None:
    if msg.arbitration_id == 0x201:
        word = struct.unpack_from("<H", msg.data)[0]
        if not words or words[-1] != word:
            words.append(word)
node = master.emulator.node
print("stopped", loop.stop_reason, node.state, abs(node.plant.velocity_deg_s),
      " ".join(hex(w) for w in words), sep="|", flush=True)
observer.shutdown()
master.close()
"""


def test_ctrl_c_quick_stops_then_disables_the_drive(run_python):
    child = run_python(CHILD)
    assert child.stdout.readline().strip() == "moving"  # at more than 300 deg/s
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=30)
    assert child.returncode == 0, err
    tag, reason, state, velocity, words = out.strip().split("|")
    assert (tag, reason, state) == ("stopped", "signal SIGINT", "SWITCH ON DISABLED")
    assert float(velocity) < 5.0  # braked from some 400 deg/s to standstill, not coasting
    assert words == "0xf 0x2 0x0"  # enable operation ... quick stop ... disable voltage
