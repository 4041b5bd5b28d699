"""CiA 306, the electronic data sheet (EDS) and device configuration file (DCF): the text of one
as hil reads it. The standard asks for ASCII; vendors write UTF-8 (Nanotec's and Ingenia's
object names) and Windows-1252 (a comment in FAULHABER's), and canopen opens a path in the
locale's encoding."""

from __future__ import annotations


def description_encoding(path: str) -> str:
    """``utf-8`` for a file that is UTF-8 (ASCII is), else ``latin-1``, which takes every
    byte."""
    with open(path, "rb") as file:
        data = file.read()
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        return "latin-1"
    return "utf-8"
