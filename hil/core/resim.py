"""What a resimulation reads of a recorded session, whatever its application: the configuration
its run recorded (the ``session`` and ``config`` metadata), the tables it ran with as a config
file a new run can be given, and the ``resim`` metadata the new session carries.

The applications rebuild their run from it (:mod:`hil.servo.resim`, :mod:`hil.bench.resim`);
what cannot be rebuilt is one :class:`~hil.errors.UsageError` line naming the file.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import tomli_w

from hil.core.recording.reader import SessionData
from hil.core.verdict import Limit, parse_limit
from hil.errors import UsageError


@dataclass(frozen=True)
class Recorded:
    """A recorded session's configuration: its file, kind (``servo``, ``bench``...), the
    config metadata (one table per part of the run) and its settings, each key's value as it
    ran (paths resolved)."""

    path: str
    kind: str
    config: dict[str, Any]

    @property
    def settings(self) -> dict[str, Any]:
        return dict(self.config.get("settings") or {})

    def table(self, name: str) -> dict[str, Any]:
        """The config metadata's table ``name`` (a deep copy); one line when it is missing."""
        table = self.config.get(name)
        if not isinstance(table, Mapping):
            raise UsageError(f"{self.path}: its recorded configuration has no {name!r} table "
                             "(a session of an older hil?): it cannot be re-simulated")
        return copy.deepcopy(dict(table))

    def limits(self, run: Mapping[str, Any]) -> tuple[Limit, ...]:
        """The limits the recorded run held (its ``limits``: config's and flags')."""
        return tuple(parse_limit(str(text)) for text in run.get("limits", []))


def read_recorded(data: SessionData, kinds: tuple[str, ...]) -> Recorded:
    """The configuration ``data`` recorded; one line when it has none or is not of ``kinds``."""
    session = data.metadata.get("session") or {}
    try:
        config = json.loads((data.metadata.get("config") or {}).get("json", "{}"))
    except json.JSONDecodeError:
        config = {}
    if not session or not isinstance(config, dict) or not config:
        raise UsageError(f"{data.path}: no run configuration recorded (metadata 'session' and "
                         "'config'): it cannot be re-simulated")
    kind = str(session.get("kind", ""))
    if kind not in kinds:
        raise UsageError(f"{data.path}: a {kind or 'unknown'} session: 'hil resim' re-runs "
                         f"{' and '.join(kinds)} sessions")
    return Recorded(data.path, kind, config)


def _leaves(tables: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for key, value in tables.items():
        if isinstance(value, Mapping):
            yield from _leaves(value, f"{prefix}{key}.")
        else:
            yield prefix + key, value


def _set(tables: dict[str, Any], key: str, value: Any) -> None:
    *heads, last = key.split(".")
    for head in heads:
        tables = tables[head]
    tables[last] = value


def resolved_paths(tables: dict[str, Any], settings: Mapping[str, Any]) -> dict[str, Any]:
    """``tables`` with every relative path the run resolved (its setting's value an absolute
    path) replaced by that path: the tables then mean the same files from any folder."""
    for key, value in list(_leaves(tables)):
        ran = (settings.get(key) or {}).get("value") if isinstance(value, str) else None
        if value and isinstance(ran, str) and os.path.isabs(ran) and not os.path.isabs(value):
            _set(tables, key, ran)
    return tables


def write_config(tables: Mapping[str, Any], folder: str, name: str) -> str:
    """``tables`` as a TOML config file ``name`` in ``folder``; its path."""
    path = os.path.join(folder, name)
    with open(path, "wb") as file:
        file.write(tomli_w.dumps(dict(tables)).encode())
    return path


def resim_metadata(recorded: str, controller: str, params: Mapping[str, Any],
                   plant: str) -> dict[str, str]:
    """The new session's ``resim`` metadata: which file it re-simulates, with which controller
    and parameters, against which plant."""
    return {"of": os.path.abspath(recorded), "controller": controller,
            "params": json.dumps(dict(params), default=str), "plant": plant}
