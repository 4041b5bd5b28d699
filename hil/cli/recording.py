"""The session-file flags shared by every command that records: encodings and splitting."""

from __future__ import annotations

import argparse

from hil.cli.argtypes import positive_float
from hil.core.recorder import ENCODINGS, RecordingOptions


def topic_encoding(text: str) -> tuple[str, str]:
    """``TOPIC=ENCODING`` of ``--topic-encoding``."""
    topic, sep, encoding = text.partition("=")
    if not sep or not topic.startswith("/") or encoding not in ENCODINGS:
        raise argparse.ArgumentTypeError(
            f"expected /TOPIC=ENCODING with ENCODING one of {', '.join(ENCODINGS)}, got {text!r}")
    return topic, encoding


def add_recording_arguments(parser: argparse.ArgumentParser) -> None:
    """``--encoding``, ``--topic-encoding``, ``--split-duration`` and ``--split-size``."""
    group = parser.add_argument_group(
        "session file", "How the session is written. High-rate topics (the 2 kHz drive topics "
        "and the MPC prediction) are CDR with a ros2msg schema by default, about a third of "
        "their JSON size; everything else is JSON. Foxglove opens both without a plug-in.")
    group.add_argument("--encoding", choices=ENCODINGS, default="cdr",
                       help="encoding of the high-rate topics (default cdr)")
    group.add_argument("--topic-encoding", type=topic_encoding, action="append", default=[],
                       metavar="/TOPIC=ENC", help="the encoding of one topic (repeatable)")
    group.add_argument("--split-duration", type=positive_float, metavar="S",
                       help="start a new file every S seconds of session time: OUT_000.mcap, "
                       "OUT_001.mcap ... (each complete and indexed; read as one session)")
    group.add_argument("--split-size", type=positive_float, metavar="MB",
                       help="start a new file when the current one reaches MB megabytes")


def recording_options(args: argparse.Namespace) -> RecordingOptions:
    """The :class:`RecordingOptions` of parsed flags."""
    return RecordingOptions(
        high_rate_encoding=args.encoding, topic_encodings=dict(args.topic_encoding),
        split_duration_s=args.split_duration, split_size_mb=args.split_size)
