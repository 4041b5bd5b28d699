"""The explicit laws these tests read, built once per test process."""

from __future__ import annotations

import functools
from collections.abc import Callable

import pytest

from hil.controllers.servo.empc import ExplicitLaw, build_explicit_law
from hil.controllers.servo.mpc import MpcConfig


@pytest.fixture(scope="session")
def explicit_law() -> Callable[[MpcConfig], ExplicitLaw]:
    """``build_explicit_law(config)`` (default model and box), once per config: the paper's law
    is read by test_mpqp, test_empc, test_empc_tree and test_empc_export, 0.6 s of CPU each
    build. A test that changes a law builds its own."""
    return functools.cache(build_explicit_law)
