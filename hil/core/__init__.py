"""The framework: clocks, the fixed-rate loop, sessions (recorder, reader), statistics,
configuration primitives, errors, the device contract and the URL scheme registry.

It names no application: the bench and the servo packages plug into it."""
