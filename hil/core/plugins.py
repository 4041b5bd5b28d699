"""Load a user's object (a controller class, a factory) from a spec string.

A spec is one of:

* ``NAME`` - registered under an entry-point group by an installed package (hil registers its
  built-in controllers the same way);
* ``FILE.py:Attribute`` - a Python file, relative to the current directory or absolute;
* ``package.module:Attribute`` - an importable module.

Every failure is a :class:`~hil.errors.ConfigError` that names the spec and the reason
(a missing file, a module that raises on import, a missing attribute), never a traceback.
"""

from __future__ import annotations

import functools
import importlib
import importlib.metadata
import importlib.util
import inspect
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.core.guard import describe_exception
from hil.errors import ConfigError, HilError


def registered_names(group: str) -> list[str]:
    """The names installed packages register in ``group``."""
    return sorted({ep.name for ep in _entry_points(group)})


def registered(group: str, name: str) -> Any | None:
    """The object installed packages register as ``name`` in ``group`` (loaded), or None."""
    for entry in _entry_points(group):
        if entry.name == name:
            return entry.load()
    return None


def _entry_points(group: str) -> tuple[importlib.metadata.EntryPoint, ...]:
    """The entry points installed packages register in ``group``, read again only once the
    packages on ``sys.path`` may have changed (:func:`_path_state`): each read opens every
    installed package's ``entry_points.txt`` (some 5 ms, a fifth of a short lockstep run's CPU
    in a process that runs many)."""
    return _entry_points_of(group, _path_state())


def _path_state() -> tuple[tuple[str, int], ...]:
    """Each folder of ``sys.path`` (the current one for ``''``) with its modification time: a
    package installed into one, or removed, changes its time, and a folder added is a new
    entry."""
    state = []
    for entry in sys.path:
        try:
            folder = entry or os.getcwd()
            state.append((folder, os.stat(folder).st_mtime_ns))
        except OSError:  # gone (the current folder too): as it is now
            state.append((entry, -1))
    return tuple(state)


@functools.lru_cache(maxsize=32)
def _entry_points_of(group: str, state: tuple[tuple[str, int], ...]
                     ) -> tuple[importlib.metadata.EntryPoint, ...]:
    return tuple(importlib.metadata.entry_points(group=group))


def _import_failure(spec: str, exc: BaseException) -> ConfigError:
    return ConfigError(f"{spec!r}: importing it failed: {describe_exception(exc)}")


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
        try:
            found = registered(group, spec)
        except Exception as exc:
            raise _import_failure(spec, exc) from None
        if found is not None:
            return found
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


CONTROLLER_GROUP = "hil.controllers"
_OTHER_METHOD = {"decide": ("step", "servo"), "step": ("decide", "bench")}


def controller_label(spec: str | Callable[..., Any]) -> str:
    """How a controller is named in KPIs, events and errors: the spec, or module:Class."""
    if isinstance(spec, str):
        return spec
    return f"{getattr(spec, '__module__', '?')}:{getattr(spec, '__qualname__', repr(spec))}"


def controller_short_name(label: str) -> str:
    """The class or built-in name of a label (``my_ctl.py:Threshold`` -> ``Threshold``), for
    file names and messages."""
    return label.rpartition(":")[2] or label


def _check_method(obj: Any, method: str, application: str, label: str) -> None:
    if callable(getattr(obj, method, None)):
        return
    other, other_app = _OTHER_METHOD.get(method, ("", ""))
    hint = (f"; it has {other}(): a {other_app} controller" if other and
            callable(getattr(obj, other, None)) else "")
    raise ConfigError(f"controller {label!r} has no {method}() method: not a {application} "
                      f"controller{hint}")


def _accepts_context(factory: Callable[..., Any]) -> bool:
    try:
        return "context" in inspect.signature(factory).parameters
    except (TypeError, ValueError):  # builtins without a signature
        return False


_SHAPES = {"bench": "Class(params)", "servo": "Class(reference, params)"}


def _check_call_shape(factory: Callable[..., Any], args: tuple[Any, ...],
                      kwargs: dict[str, Any], label: str, application: str) -> None:
    """A factory that cannot take the application's arguments is named, with its signature."""
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):
        return
    try:
        signature.bind(*args, **kwargs)
    except TypeError:
        names = ", ".join(signature.parameters)
        raise ConfigError(f"controller {label!r} is built as {controller_short_name(label)}"
                          f"({names}), but a {application} controller is built as "
                          f"{_SHAPES.get(application, '?')}") from None


def controller_factory(spec: str | Callable[..., Any], *args: Any, method: str,
                       application: str) -> tuple[Callable[..., Any], str]:
    """The factory named by ``spec`` (a spec string or a class/factory), checked before
    anything is built: it can be called with ``args`` (and ``context=``, if it takes one), and
    a class has ``method``. Returns (factory, label)."""
    label = controller_label(spec)
    factory = load_object(spec, CONTROLLER_GROUP) if isinstance(spec, str) else spec
    if not callable(factory):
        raise ConfigError(f"controller {label!r} is a {type(factory).__name__}, not a class")
    if isinstance(factory, type):
        _check_method(factory, method, application, label)
    kwargs = {"context": None} if _accepts_context(factory) else {}
    _check_call_shape(factory, args, kwargs, label, application)
    return factory, label


def build_controller(factory: Callable[..., Any], label: str, *args: Any, method: str,
                     application: str, context: Any = None) -> Any:
    """``factory(*args)`` (with ``context=context`` when it takes one); the result must have
    ``method``. A failure is a ConfigError naming the controller and the reason."""
    kwargs = {"context": context} if _accepts_context(factory) else {}
    try:
        controller = factory(*args, **kwargs)
    except HilError:
        raise
    except Exception as exc:
        raise ConfigError(f"controller {label!r}: building it failed: "
                          f"{describe_exception(exc)}") from None
    _check_method(controller, method, application, label)
    return controller
