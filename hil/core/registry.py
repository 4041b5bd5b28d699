"""URL scheme -> device factory, loaded lazily (python-can's interface table).

An application declares its table of built-in schemes as ``scheme -> (module, attribute)``;
installed packages add schemes through an entry-point group. A factory's module is imported
only when a URL with its scheme is opened, so ``hil`` does not import pymodbus to run the drive
or python-can to run the bench. The registry itself names no application.

The scheme of ``modbus-tcp://127.0.0.1:5020`` is ``modbus-tcp``; a URL without ``://`` (such
as ``emulated``) is its own scheme.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from hil.errors import ConfigError

if TYPE_CHECKING:
    import importlib.metadata

Factory = Callable[..., Any]


def scheme_of(url: str) -> str:
    """``modbus-tcp`` of ``modbus-tcp://H:P``; ``emulated`` of ``emulated``."""
    scheme, sep, _rest = url.partition("://")
    return scheme if sep else url


class SchemeRegistry:
    """The device factories of one kind of device (``bench``, ``drive``), by URL scheme.

    ``fallback`` (optional) takes any scheme the table does not name and returns a factory or
    None: the drive uses it for every python-can interface (``pcan://...``, ``kvaser://...``).
    """

    def __init__(self, kind: str, builtin: Mapping[str, tuple[str, str]],
                 entry_point_group: str | None = None,
                 fallback: Callable[[str], Factory | None] | None = None) -> None:
        self.kind = kind
        self.builtin = dict(builtin)
        self.entry_point_group = entry_point_group
        self.fallback = fallback

    def _installed(self) -> dict[str, importlib.metadata.EntryPoint]:
        if self.entry_point_group is None:
            return {}
        import importlib.metadata  # here: a built-in scheme reads no package metadata

        return {ep.name: ep for ep in importlib.metadata.entry_points(group=self.entry_point_group)}

    def schemes(self) -> list[str]:
        """Every scheme named by the table or an installed package."""
        return sorted({*self.builtin, *self._installed()})

    def factory(self, url: str) -> Factory:
        """The factory for ``url``; a ConfigError names the URL and the known schemes."""
        scheme = scheme_of(url)
        if scheme in self.builtin:
            module_name, attribute = self.builtin[scheme]
            factory: Factory = getattr(importlib.import_module(module_name), attribute)
            return factory
        installed = self._installed()
        if scheme in installed:
            loaded: Factory = installed[scheme].load()
            return loaded
        found = self.fallback(scheme) if self.fallback is not None else None
        if found is not None:
            return found
        raise ConfigError(f"{self.kind} '{url}': unknown scheme '{scheme}' (known: "
                          f"{', '.join(self.schemes())})")

    def open(self, url: str, *args: Any, **kwargs: Any) -> Any:
        """``factory(url)(url, *args, **kwargs)``."""
        return self.factory(url)(url, *args, **kwargs)
