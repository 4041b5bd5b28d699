"""The settings a run writes to a drive, each put back when the master lets the drive go; a
journal on disk for those that could not be.

Before a setting is written (:meth:`RunSettings.write`: the master's ``_write_setting``), the
value the drive holds is read and kept; when the master lets the drive go
(:meth:`RunSettings.restore`), every one is written back, last first, so a sequence the drive
checks (CiA 301's PDO remapping) is undone in the order that allows it.

A drive on a bus (not the in-process emulator, which ends with the run) also has a journal: a
small JSON file per drive in :func:`journal_folder`, named by the bus, the node id and the
drive's identity (0x1018), written before the drive is. It is removed once everything is back.
When the link is lost and the drive still silent at the close, the file stays, and the next
master that opens that drive (:meth:`RunSettings.open`) puts back each setting the drive still
holds at the value the earlier run wrote: a setting with another value now was changed since (a
power cycle, a commissioning tool) and is left as it is. Either way an event says what.

The journal lives with the user, not with the sessions (``HIL_STATE_DIR``, default
``$XDG_STATE_HOME/hil``, i.e. ``~/.local/state/hil``): the next run finds it whatever its working
folder or ``--out``. It is no substitute for the drive's own memory: a setting the drive keeps
(stored with 0x1010) is never written by hil.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from hil.drivers.canopen.errors import DriveError
from hil.drivers.canopen.identity import Identity, read_identity
from hil.drivers.canopen.sdo import SdoChannel
from hil.protocols.cia301 import SdoAbortError
from hil.protocols.cia402 import OPERATION_MODES

STATE_DIR_ENV = "HIL_STATE_DIR"
JOURNAL_FORMAT = "hil.drive-settings/1"
Event = Callable[..., None]  # the master's _event(kind, message, level=..., **data)
#: the modes' set points (targets): commands, not settings; they keep the run's last value
SET_POINTS = frozenset(mode.set_point[:2] for mode in OPERATION_MODES.values()
                       if mode.set_point is not None)


def journal_folder() -> str:
    """Where journals of settings left on drives are kept: ``$HIL_STATE_DIR/drive-settings``,
    by default under ``$XDG_STATE_HOME/hil`` (``~/.local/state/hil``)."""
    state = os.environ.get(STATE_DIR_ENV) or os.path.join(
        os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local",
                                                         "state"), "hil")
    return os.path.join(state, "drive-settings")


@dataclass(frozen=True)
class Setting:
    """One write of a run: the object, its wire format, the value found and the one written."""

    index: int
    subindex: int
    fmt: str
    found: int
    written: int

    @property
    def name(self) -> str:
        return f"0x{self.index:04X}:{self.subindex:02X}"

    @property
    def key(self) -> tuple[int, int]:
        return self.index, self.subindex


class RunSettings:
    """The settings written to node ``node_id`` through ``sdo``; ``event`` is the master's."""

    def __init__(self, sdo: SdoChannel, node_id: int, event: Event) -> None:
        self.sdo, self.node_id, self._event = sdo, node_id, event
        self.log: list[Setting] = []
        #: what :meth:`open` put back of an earlier run's, as one line (None: nothing)
        self.restored: str | None = None
        #: the drive's 0x1018 as read at :meth:`open` (None: not journaled, never read)
        self.identity: Identity | None = None
        self._folder: str | None = None
        self._bus = ""
        self._path: str | None = None
        self._drive: dict[str, Any] = {}

    def keep_journal(self, bus: str, folder: str | None = None) -> None:
        """Journal this drive on disk, as the drive of node ``node_id`` on ``bus`` (its URL),
        in ``folder`` (default: :func:`journal_folder`)."""
        self._bus, self._folder = bus, folder or journal_folder()

    # -- the master's life cycle -----------------------------------------------------------
    def open(self) -> None:
        """Who the drive is (0x1018), and what an earlier run left on it, put back: once,
        before this run writes its first setting (the master's open, or a write before it)."""
        if self._folder is None or self._path is not None:
            return
        self.identity = identity = read_identity(self.sdo)
        self._drive = {"bus": self._bus, "node": self.node_id, "identity": identity.as_dict()}
        key = json.dumps(self._drive, sort_keys=True)
        self._path = os.path.join(self._folder,
                                  hashlib.sha256(key.encode()).hexdigest()[:24] + ".json")
        left = self._load()
        if left is not None:
            self._restore_leftover(*left)

    def stranger(self) -> Identity | None:
        """The drive now answering when it is not the one :meth:`open` read (0x1018 read
        again: another drive at the bus's URL since); None when it is, or when none was read
        at open. A DriveError when the drive does not answer."""
        if self.identity is None:
            return None
        now = read_identity(self.sdo)
        return None if now == self.identity else now

    def write(self, index: int, subindex: int, value: int, fmt: str) -> None:
        """Write one setting, the value it replaces kept first (in the journal too); a set
        point (a mode's target) is written as it is."""
        self.open()
        if (index, subindex) in SET_POINTS:
            self.sdo.write(index, subindex, value, fmt)
            return
        try:
            setting = Setting(index, subindex, fmt, self.sdo.read_int(index, subindex, fmt), value)
        except SdoAbortError as exc:  # write-only: what it held cannot be known
            self._event("drive.setting_unrecorded", f"drive node {self.node_id}: 0x{index:04X}:"
                        f"{subindex:02X} cannot be read ({exc}): the value this run writes "
                        "stays on the drive", level="warning", index=index, subindex=subindex)
            self.sdo.write(index, subindex, value, fmt)
            return
        self.log.append(setting)
        self._save(self.log)
        try:
            self.sdo.write(index, subindex, value, fmt)
        except SdoAbortError:  # refused: nothing to put back
            self.log.remove(setting)
            self._save(self.log)
            raise

    def restore(self) -> None:
        """Every setting of this run back to the value found, last first (a link lost: at
        most one SDO time-out is waited for a drive that stays silent, and its journal
        stays for the next open). Silent when all is back."""
        log, self.log = self.log, []
        for done, setting in enumerate(reversed(log)):
            if setting.found == setting.written:
                continue
            try:
                self.sdo.write(*setting.key, setting.found, setting.fmt,
                               timeout_s=self.sdo.timeout_s)
            except SdoAbortError as exc:
                self._event("drive.setting_kept", f"drive node {self.node_id}: {setting.name} "
                            f"refused its own value {setting.found} back ({exc}): it stays at "
                            f"this run's {setting.written}", level="warning",
                            index=setting.index, subindex=setting.subindex)
            except DriveError as exc:
                left = log[:len(log) - done]
                self._save(left)
                where = f"; the next run on it puts them back ({self._path})" \
                    if self._path else ""
                self._event("drive.settings_left", f"drive node {self.node_id}: "
                            f"{len(left)} setting(s) of this run stay on the drive, which "
                            f"does not answer ({exc}): {_listed(left)}{where}",
                            level="error", settings=[asdict(s) for s in left])
                return
        self._remove()

    # -- the journal on disk -----------------------------------------------------------------
    def _save(self, log: list[Setting]) -> None:
        """The journal as it stands (written whole, never half: a temporary file renamed)."""
        if self._path is None:
            return
        if not log:
            self._remove()
            return
        document = {"format": JOURNAL_FORMAT, **self._drive, "pid": os.getpid(),
                    "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                    "settings": [asdict(s) for s in log]}
        try:
            os.makedirs(os.path.dirname(self._path), exist_ok=True)
            with tempfile.NamedTemporaryFile("w", dir=os.path.dirname(self._path),
                                             prefix=".journal-", delete=False) as out:
                json.dump(document, out, indent=1)
            os.replace(out.name, self._path)
        except OSError as exc:
            raise DriveError(f"drive node {self.node_id}: cannot keep the journal of this "
                             f"run's settings ({self._path}: {exc.strerror}); set "
                             f"{STATE_DIR_ENV} to a writable folder") from None

    def _remove(self) -> None:
        if self._path is not None:
            with contextlib.suppress(FileNotFoundError):
                os.remove(self._path)

    def _load(self) -> tuple[list[Setting], dict[str, Any]] | None:
        """The settings an earlier run left on this drive, and its journal (None: none)."""
        assert self._path is not None
        try:
            with open(self._path, encoding="utf-8") as file:
                document = json.load(file)
            settings = [Setting(**entry) for entry in document["settings"]]
        except FileNotFoundError:
            return None
        except (OSError, ValueError, TypeError, KeyError) as exc:
            self._event("drive.journal_unreadable", f"drive node {self.node_id}: the journal "
                        f"{self._path} cannot be read ({exc}): set aside", level="warning")
            with contextlib.suppress(OSError):
                os.replace(self._path, self._path + ".unreadable")
            return None
        return settings, document

    def _restore_leftover(self, left: list[Setting], document: dict[str, Any]) -> None:
        """Each object the drive still holds at the value the earlier run last wrote: its
        writes undone, last first; the others were changed since and stay."""
        last = {setting.key: setting for setting in left}
        still = {key for key, setting in last.items()
                 if self.sdo.read_int(*key, setting.fmt) == setting.written}
        back = [s for s in reversed(left) if s.key in still and s.found != s.written]
        for setting in back:
            self.sdo.write(*setting.key, setting.found, setting.fmt)
        changed = [last[key] for key in last if key not in still]
        self._remove()
        run = f"pid {document.get('pid', '?')}, {document.get('written', 'time unknown')}"
        self.restored = (f"drive node {self.node_id}: put back what an earlier run ({run}) "
                         f"left on it: {_listed(back, undone=True) or 'nothing'}" +
                         (f"; changed since, left as they are: "
                          f"{', '.join(s.name for s in changed)}" if changed else ""))
        self._event("drive.settings_restored", self.restored, level="warning",
                    restored=[asdict(s) for s in back], changed=[asdict(s) for s in changed])


def _listed(settings: list[Setting], undone: bool = False) -> str:
    """``0x6072:00 300 -> 1000, ...`` (undone: from the value written to the one found)."""
    return ", ".join(f"{s.name} {s.written} -> {s.found}" if undone else
                     f"{s.name} = {s.written} (was {s.found})" for s in settings)

