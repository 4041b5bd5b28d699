"""The controllers' errors. Both are :class:`~hil.errors.HilError`, so the command line prints
each as one line; neither says anything about a command line or a file the user wrote."""

from __future__ import annotations

from hil.errors import ConfigError, HilError


class ControllerSetupError(ConfigError):
    """A controller's setting, model or reference is wrong; the message names it and its unit."""


class SolverError(HilError):
    """An offline computation failed (a QP or an LP, the explicit MPC's partition), or its
    result cannot be written."""
