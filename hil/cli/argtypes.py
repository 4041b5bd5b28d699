"""argparse value types whose errors name the problem in one line."""

from __future__ import annotations

import argparse


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


def node_id(text: str) -> int:
    """A CANopen node id: 1..127 (CiA 301)."""
    from hil.protocols.cia301 import MAX_NODE_ID

    value = positive_int(text)
    if value > MAX_NODE_ID:
        raise argparse.ArgumentTypeError(f"a CANopen node id is 1..{MAX_NODE_ID}, got {value}")
    return value


def positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}") from None
    if not value > 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a positive finite number, got {text}")
    return value


def nonnegative_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}") from None
    if not value >= 0 or value == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a finite number >= 0, got {text}")
    return value


def host_port(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (IPv6 as ``[::1]:PORT``)."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not host:
        raise argparse.ArgumentTypeError(f"expected HOST:PORT, got {text!r}")
    host = host.strip("[]")
    try:
        port = int(port_text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port must be a number in {text!r}") from None
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"port {port} out of range 0-65535 in {text!r}")
    return host, port


def key_value(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` (e.g. of ``--safety``), the value parsed as a number or a boolean."""
    from hil.core.params import parse_value

    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    return key.strip(), parse_value(value.strip())


def output_file(text: str) -> str:
    """A file a command will write: its missing folders are created here, at parsing, so a
    path that cannot be written is refused before anything runs or any hardware is reached."""
    from hil.core.recording.output import output_problem

    if not text:
        raise argparse.ArgumentTypeError("expected a file name, got ''")
    problem = output_problem(text)
    if problem is not None:
        raise argparse.ArgumentTypeError(problem)
    return text
