"""hil: a hardware-in-the-loop bridge (fixed-rate loop, clocks, MCAP sessions, CLI)."""

__version__ = "0.1.0"
