"""Load a user's object (a controller class, a factory) from a spec string.

A spec is one of:

* ``NAME`` - registered under an entry-point group by an installed package (hil registers its
  built-in controllers the same way);
* ``FILE.py:Attribute`` - a Python file, relative to the current directory or absolute;
* ``package.module:Attribute`` - an importable module.

Every failure is a :class:`~hil.core.errors.ConfigError` that names the spec and the reason
(a missing file, a module that raises on import, a missing attribute), never a traceback.
"""

from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import sys
import traceback
from pathlib import Path
from typing import Any

from hil.core.errors import ConfigError


def registered_names(group: str) -> list[str]:
    """The names installed packages register in ``group``."""
    return sorted({ep.name for ep in importlib.metadata.entry_points(group=group)})


def _import_failure(spec: str, exc: BaseException) -> ConfigError:
    """The spec and the last line of where its import failed (file:line: error)."""
    frames = traceback.extract_tb(exc.__traceback__)
    where = f" ({Path(frames[-1].filename).name}:{frames[-1].lineno})" if frames else ""
    return ConfigError(f"{spec!r}: importing it failed{where}: {type(exc).__name__}: {exc}")


def _load_file(spec: str, file_part: str) -> Any:
    path = Path(file_part).expanduser()
    if not path.is_file():
        raise ConfigError(f"{spec!r}: no such file {str(path)!r} (relative to "
                          f"{Path.cwd()})")
    name = f"hil_user_{path.stem}_{abs(hash(str(path.resolve()))):x}"
    if name in sys.modules:
        return sys.modules[name]
    module_spec = importlib.util.spec_from_file_location(name, path)
    if module_spec is None or module_spec.loader is None:
        raise ConfigError(f"{spec!r}: {str(path)!r} is not a Python file")
    module = importlib.util.module_from_spec(module_spec)
    sys.modules[name] = module
    try:
        module_spec.loader.exec_module(module)
    except BaseException as exc:
        del sys.modules[name]
        if isinstance(exc, KeyboardInterrupt | SystemExit):
            raise
        raise _import_failure(spec, exc) from None
    return module


def _load_module(spec: str, module_name: str) -> Any:
    try:
        return importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name and module_name.startswith(exc.name):
            raise ConfigError(f"{spec!r}: no module named {module_name!r}") from None
        raise _import_failure(spec, exc) from None
    except Exception as exc:
        raise _import_failure(spec, exc) from None


def load_object(spec: str, group: str) -> Any:
    """The object named by ``spec`` (see the module docstring); ``group`` is the entry-point
    group searched for a bare name."""
    spec = spec.strip()
    if not spec:
        raise ConfigError("an empty spec: give NAME, FILE.py:Class or package.module:Class")
    location, sep, attribute = spec.rpartition(":")
    if not sep:
        for entry in importlib.metadata.entry_points(group=group):
            if entry.name == spec:
                try:
                    return entry.load()
                except Exception as exc:
                    raise _import_failure(spec, exc) from None
        known = ", ".join(registered_names(group)) or "none"
        raise ConfigError(f"{spec!r}: no such name (registered: {known}); a file or module "
                          "is named FILE.py:Class or package.module:Class")
    if not location or not attribute.isidentifier():
        raise ConfigError(f"{spec!r}: expected NAME, FILE.py:Class or package.module:Class")
    is_file = location.endswith(".py") or "/" in location or "\\" in location
    module = _load_file(spec, location) if is_file else _load_module(spec, location)
    try:
        return getattr(module, attribute)
    except AttributeError:
        public = sorted(n for n in vars(module) if not n.startswith("_") and
                        isinstance(getattr(module, n), type))
        raise ConfigError(f"{spec!r}: {location} has no {attribute!r} (classes there: "
                          f"{', '.join(public) or 'none'})") from None
