"""The drive description files vendors publish (tests/data/drives/<vendor>/, their table in its
README.md), which hil's tests use as the files users bring: each parses with canopen as a CiA 402
drive, and none is there without its provenance. The ``SOURCE.md`` beside a file gives, in one
table per file, where it comes from, its licence and its sha256, which must match the bytes
committed; the README's table names it."""

from __future__ import annotations

import hashlib
import logging
import re
from pathlib import Path

import canopen
import pytest

DRIVES = Path(__file__).resolve().parents[2] / "data" / "drives"
FILES = sorted(path for path in DRIVES.glob("*/*") if path.suffix.lower() in (".eds", ".dcf"))
FIELDS = {"file", "sha256", "repository", "path", "commit", "URL", "licence", "describes"}
CIA402_CORE = (0x6040, 0x6041, 0x6060, 0x6061, 0x6064)  # control/statusword, mode, position
NODE = 5
ROW = re.compile(r"^\| (?P<field>[^|]+?) \| (?P<value>.+) \|$")


def label(path: Path) -> str:
    return f"{path.parent.name}/{path.name}"


def provenance(source_md: Path) -> dict[str, dict[str, str]]:
    """The tables of a SOURCE.md, one per file: field -> value, by the file's name."""
    tables: dict[str, dict[str, str]] = {}
    for block in source_md.read_text(encoding="utf-8").split("\n## ")[1:]:
        rows = dict(match.group("field", "value") for line in block.splitlines()
                    if (match := ROW.match(line)))
        tables[rows.get("file", "").strip("`")] = rows
    return tables


def text_encoding(path: Path) -> str:
    """UTF-8 where the bytes are; else Latin-1, which decodes any byte (FAULHABER's file has a
    DOS code-page umlaut, on which canopen's ``import_od(path)`` fails under UTF-8)."""
    try:
        path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        return "latin-1"
    return "utf-8"


def test_the_files_come_from_at_least_five_vendors():
    assert len({path.parent for path in FILES}) >= 5, FILES


@pytest.mark.parametrize("path", FILES, ids=label)
def test_each_file_parses_with_canopen_as_a_cia402_drive(path, caplog):
    with caplog.at_level(logging.WARNING, logger="canopen"), \
            path.open(encoding=text_encoding(path)) as stream:
        od = canopen.import_od(stream, NODE)
    # canopen's own warnings only (another test's CAN bus collected meanwhile logs its own)
    warned = [record.getMessage() for record in caplog.records
              if record.name.startswith("canopen")]
    assert not warned, warned
    assert [f"0x{index:04X}" for index in CIA402_CORE if index not in od] == []


@pytest.mark.parametrize("path", FILES, ids=label)
def test_each_file_has_its_source_licence_and_checksum_beside_it(path):
    source = path.parent / "SOURCE.md"
    assert source.is_file(), f"{label(path)} has no SOURCE.md beside it"
    entry = provenance(source).get(path.name)
    assert entry is not None, f"{source} has no table for {path.name}"
    assert entry.keys() >= FIELDS, f"{source}, {path.name}: lacks {FIELDS - entry.keys()}"
    assert entry["sha256"] == f"`{hashlib.sha256(path.read_bytes()).hexdigest()}`", \
        f"{label(path)} is not the file its SOURCE.md describes"
    assert f"`{label(path)}`" in (DRIVES / "README.md").read_text(encoding="utf-8")


def test_every_file_a_source_names_is_committed():
    named = {(source.parent / name) for source in DRIVES.glob("*/SOURCE.md")
             for name in provenance(source)}
    assert named == set(FILES)
