"""The wire protocols as data, shared by the drivers (hil's side) and the emulators (the
device's side): CiA 301 and CiA 402 tables, CAN frames, and the clock map of hil's bench
emulator. Imports only the standard library, python-can and :mod:`hil.errors`."""
