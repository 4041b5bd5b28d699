"""The session flags shared by every command that records: encodings, splitting, live view."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from typing import TypeVar

from hil.cli.argtypes import positive_float
from hil.core.recording.live import DEFAULT_RATE_HZ, check_bindable, parse_address, parse_rate
from hil.core.recording.recording_options import ENCODINGS, RecordingOptions
from hil.errors import UsageError

T = TypeVar("T")


def topic_encoding(text: str) -> tuple[str, str]:
    """``TOPIC=ENCODING`` of ``--topic-encoding``."""
    topic, sep, encoding = text.partition("=")
    if not sep or not topic.startswith("/") or encoding not in ENCODINGS:
        raise argparse.ArgumentTypeError(
            f"expected /TOPIC=ENCODING with ENCODING one of {', '.join(ENCODINGS)}, got {text!r}")
    return topic, encoding


def _argparse_type(parse: Callable[[str], T]) -> Callable[[str], T]:
    """A ``hil.core.recording.live`` parser as an argparse type (its UsageError as argparse's
    error)."""
    def convert(text: str) -> T:
        try:
            return parse(text)
        except UsageError as exc:
            raise argparse.ArgumentTypeError(str(exc).partition(": ")[2]) from None
    return convert


def add_live_arguments(parser: argparse.ArgumentParser, *, rates: bool = True,
                       tuning: bool = True) -> None:
    """``--live [HOST:]PORT``, (``rates``) ``--live-rate /TOPIC=HZ`` and, for a live view that
    serves a run's parameters (``tuning``), ``--allow-remote-tuning``."""
    group = parser.add_argument_group(
        "live view", "Serve the session's topics over the Foxglove WebSocket protocol while it "
        "runs (Foxglove: Open connection > Foxglove WebSocket; PlotJuggler: Foxglove "
        "WebSocket client), beside the file, from the writer process.")
    group.add_argument("--live", type=_argparse_type(parse_address), metavar="[HOST:]PORT",
                       help="serve here (host 127.0.0.1 unless given; the URL is printed)")
    if rates:
        group.add_argument("--live-rate", type=_argparse_type(parse_rate), action="append",
                           default=[], metavar="/TOPIC=HZ",
                           help=f"messages per second of session time served on TOPIC "
                           f"(default {DEFAULT_RATE_HZ:g}; 0: every one; /events: every one)")
    if tuning:
        group.add_argument("--allow-remote-tuning", action="store_true",
                           help="let the clients of a live view that listens beyond loopback "
                           "(--live 0.0.0.0:PORT) set the run's parameters; without it they "
                           "are read-only there (on loopback, clients may always set them)")


def live_address(args: argparse.Namespace) -> str | None:
    """``--live`` as ``HOST:PORT``, checked to be free now (a one-line error otherwise)."""
    if getattr(args, "live", None) is None:
        return None
    host, port = args.live
    check_bindable(host, port)
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def add_recording_arguments(parser: argparse.ArgumentParser) -> None:
    """``--encoding``, ``--topic-encoding``, ``--split-duration``, ``--split-size``, and the
    live view's ``--live`` and ``--live-rate``."""
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
    add_live_arguments(parser)


def recording_options(args: argparse.Namespace) -> RecordingOptions:
    """The :class:`RecordingOptions` of parsed flags."""
    return RecordingOptions(
        high_rate_encoding=args.encoding, topic_encodings=dict(args.topic_encoding),
        split_duration_s=args.split_duration, split_size_mb=args.split_size,
        live=live_address(args), live_rates=dict(args.live_rate),
        live_remote_tuning=args.allow_remote_tuning)
