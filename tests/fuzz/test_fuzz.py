"""The bounded fuzz campaign: every byte parser hil owns, a fixed set of cases each (the same
on every run: a fuzz test that fails now and then would be a red CI), under the rule of
:mod:`tests.fuzz.harness`. ``benchmarks/fuzz.py`` runs the same targets for longer."""

from __future__ import annotations

import pytest

from tests.fuzz.harness import Target, run_target
from tests.fuzz.targets import TARGETS

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]


@pytest.mark.parametrize("target", TARGETS, ids=lambda target: target.name)
def test_fuzzed_input_never_breaks_the_rule(target: Target) -> None:
    run_target(target)
