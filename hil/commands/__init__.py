"""One module per command group; each has ``register(subparsers)``."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from hil.errors import NotYetAvailableError


def not_yet_available(what: str) -> Callable[[argparse.Namespace], int]:
    """Handler for a command whose issue has not landed yet."""

    def handler(_args: argparse.Namespace) -> int:
        raise NotYetAvailableError(f"'{what}' is not yet available in this version of hil")

    return handler
