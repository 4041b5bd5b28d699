"""A damaged session loses at most a bounded part: a lockstep file as little session time as a
real-time one. Files recorded by ``hil`` runs (a lockstep bench cycle, 28 s of session time in
a few seconds; a real-time servo run) are cut and overwritten (4 KiB of zeros) at many offsets:
every message outside the chunks the damage touched is read back, a touched chunk loses at most
the session time a chunk spans (less what is salvaged before its damage), nothing read back is
foreign to the original, and the damage is never called intact, its count never wrong."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from hil.core.recording.reader import read_session
from tests.cli import hil_in
from tests.drive_processes import patient_watchdogs
from tests.session_damage import (
    CHUNK_SPAN_S,
    OVERWRITE_BYTES,
    chunk_places,
    damage_report,
    items_of,
    offsets,
)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]
ROOT = Path(__file__).resolve().parents[2]
OFFSETS = 20
# a loaded machine must not end the real-time run early: watchdogs far beyond its length
PATIENT = patient_watchdogs(safety="enabled = false\n")


def hil(folder: Path, *argv: str) -> None:
    subprocess.run([sys.executable, "-m", "hil", *argv], cwd=folder, timeout=120,
                   capture_output=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
                   check=False)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("damaged")


@pytest.fixture(scope="module")
def lockstep(folder: Path) -> Path:
    """Recorded in this process (the file is what these tests read, not how it was started)."""
    hil_in(folder, "bench", "run", "--controller", "bc", "--cycles", "1", "--out",
           "lockstep.mcap")
    return folder / "lockstep.mcap"


@pytest.fixture(scope="module")
def realtime(folder: Path) -> Path:
    """A real-time servo run of 1.5 s, in this process: five chunks or so (each closed after
    a second of wall time or of session time, whichever comes first)."""
    (folder / "patient.toml").write_text(PATIENT)
    hil_in(folder, "servo", "run", "--controller", "pid", "--realtime", "--duration", "1.5",
           "--config", "patient.toml", "--out", "realtime.mcap")
    return folder / "realtime.mcap"


def test_a_lockstep_session_is_chunked_by_its_own_time(lockstep):
    places = chunk_places(lockstep)
    duration_s = (places[-1].end_ns - places[0].start_ns) / 1e9
    assert duration_s > 27  # one machine cycle, recorded in a few seconds of wall time
    assert len(places) >= duration_s / CHUNK_SPAN_S
    assert all(p.end_ns - p.start_ns < CHUNK_SPAN_S * 1e9 for p in places)


@pytest.mark.parametrize("kind", ["lockstep", pytest.param("realtime",
                                                         marks=pytest.mark.realtime)])
@pytest.mark.parametrize("damage", ["cut", "overwrite"])
def test_damage_anywhere_loses_at_most_a_chunk_of_session_time(request, tmp_path, kind,
                                                               damage):
    path = request.getfixturevalue(kind)
    intact = read_session(path)
    assert not intact.recovered and not intact.damage
    original, places = items_of(intact), chunk_places(path)
    assert len(places) >= 2
    blob = path.read_bytes()
    summary_start = max(p.end for p in places)
    copy = tmp_path / "copy.mcap"
    salvaged = 0
    for first in offsets(len(blob), OFFSETS):
        last = None if damage == "cut" else first + OVERWRITE_BYTES
        copy.write_bytes(blob[:first] if last is None else
                         blob[:first] + bytes(OVERWRITE_BYTES) + blob[last:])
        report = damage_report(original, places, copy, first, last)
        where = f"{damage} at byte {first} of {len(blob)}: {report}"
        assert report.said_recovered, where
        assert report.foreign == 0, where     # nothing damaged is read back as a message
        assert report.outside == 0, where     # the chunks it did not touch are whole
        assert report.touched <= (1 if last is None else 2), where
        assert all(span < CHUNK_SPAN_S for span in report.lost_span_s), where
        if last is None or last <= summary_start:
            assert report.said_lost is None or report.said_lost == report.lost, where
        if last is not None and last <= summary_start:
            assert report.said_lost == report.lost, where  # the file's statistics tell
        salvaged += report.salvaged
    if kind == "realtime":  # chunks of ~4000 messages: the part before the damage is read
        assert salvaged > 0
