"""Every target of the campaign, in one table (the bounded test and benchmarks/fuzz.py)."""

from __future__ import annotations

from tests.fuzz import (
    bench_driver,
    bench_emulator,
    drive_emulator,
    drive_master,
    files,
    mcap_reader,
    socketcand,
)
from tests.fuzz.harness import Target

TARGETS: tuple[Target, ...] = (
    *bench_emulator.TARGETS,
    *bench_driver.TARGETS,
    *drive_emulator.TARGETS,
    *drive_master.TARGETS,
    *socketcand.TARGETS,
    *mcap_reader.TARGETS,
    *files.TARGETS,
)
