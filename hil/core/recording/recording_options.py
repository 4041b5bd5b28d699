"""How a session is recorded, as a run's options say it (``--encoding``, ``--split-*``,
``--live``): a light module of its own, so the command line builds its options without
importing the recorder's machinery."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from hil.core.recording.live import parse_address
from hil.core.recording.output import series_file
from hil.errors import HilError

ENCODINGS = ("json", "cdr")


@dataclass(frozen=True)
class RecordingOptions:
    """How a session is written: per-topic encodings, file splitting, and the live view
    (``live``: serve the topics at ``[HOST:]PORT``, see :mod:`hil.core.recording.live`;
    ``live_remote_tuning``: its clients may set the run's parameters even when it listens
    beyond loopback); ``in_process``: no writer process, the session written on the loop's
    thread (lockstep only, without a live view; no flag: ``hil sweep`` records its trials on
    Ray so, see :mod:`hil.core.recording.in_process`)."""

    #: the command-line flag of each field
    FLAGS: ClassVar[dict[str, str]] = {
        "high_rate_encoding": "--encoding", "topic_encodings": "--topic-encoding",
        "split_duration_s": "--split-duration", "split_size_mb": "--split-size",
        "live": "--live", "live_rates": "--live-rate",
        "live_remote_tuning": "--allow-remote-tuning"}

    high_rate_encoding: str = "cdr"       # for topics registered with ``high_rate=True``
    topic_encodings: dict[str, str] = field(default_factory=dict)  # explicit, by topic name
    split_duration_s: float | None = None
    split_size_mb: float | None = None
    live: str | None = None                # "[HOST:]PORT": serve the topics live (recording.live)
    live_rates: dict[str, float] = field(default_factory=dict)  # topic -> Hz (0: every message)
    live_remote_tuning: bool = False       # clients beyond loopback may set parameters
    in_process: bool = False               # no writer process (lockstep, no live view)

    def __post_init__(self) -> None:
        for name, encoding in [("high-rate topics", self.high_rate_encoding),
                               *self.topic_encodings.items()]:
            if encoding not in ENCODINGS:
                raise HilError(f"encoding of {name}: {encoding!r} is not one of "
                               f"{', '.join(ENCODINGS)}")
        for name, value in (("split duration", self.split_duration_s),
                            ("split size", self.split_size_mb)):
            if value is not None and not value > 0:
                raise HilError(f"{name} must be > 0, got {value!r}")
        if self.live is not None:
            parse_address(self.live)
        for topic, hz in self.live_rates.items():
            if not hz >= 0:
                raise HilError(f"live rate of {topic} must be >= 0 Hz, got {hz!r}")

    @property
    def split(self) -> bool:
        return self.split_duration_s is not None or self.split_size_mb is not None

    def first_file(self, path: str) -> str:
        """The file a session at ``path`` starts with (``OUT_000.mcap`` when split); any
        reader of hil takes it for the whole series."""
        return series_file(path, 0) if self.split else path
