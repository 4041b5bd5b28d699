"""The framework: clocks, the fixed-rate loop, the run pipeline, sessions (recording and reading
them: :mod:`hil.core.recording`), statistics, configuration primitives, limits and verdicts, and
the URL scheme registry.

It names no application: the bench and the servo packages plug into it."""
