"""A model file (``hil identify``'s format) read for an emulator to run: one error kind, naming
the file, whatever is wrong with it."""

from __future__ import annotations

from hil.controllers.ident.model_file import loads_model
from hil.controllers.ident.n4sid import IdentificationError, IdentifiedModel
from hil.emulators.errors import EmulatorSetupError


def read_model_file(path: str) -> IdentifiedModel:
    """The model in the file at ``path``; EmulatorSetupError naming the file and the problem
    (no such file, not readable, not a model file)."""
    try:
        with open(path, encoding="utf-8") as file:
            text = file.read()
    except FileNotFoundError:
        raise EmulatorSetupError(f"{path}: no such model file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise EmulatorSetupError(f"{path}: cannot read it: {exc}") from None
    try:
        return loads_model(text)
    except IdentificationError as exc:
        raise EmulatorSetupError(f"{path}: {exc}") from None
