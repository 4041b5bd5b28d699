"""hil's ``hil_bench`` / ``hil_drive`` fixtures on a labgrid target: with labgrid's pytest
plugin and ``--lg-env ENV.yaml`` (or ``LG_ENV``), the device of a fixture is the ``HilBench``
/ ``HilDrive`` resource of the environment's ``main`` target (labgrid's ``target`` fixture;
a ``RemotePlace`` there brings a place's resources, the place acquired beforehand with
``labgrid-client -p NAME acquire``)."""

from __future__ import annotations

from typing import Any

import pytest
from labgrid.exceptions import NoResourceFoundError
from labgrid.pytestplugin.hooks import LABGRID_ENV_KEY

from hil.lab.resources import HilBench, HilDrive

#: fixture -> its resource class and the run options its fields set
RESOURCES: dict[str, tuple[type[Any], dict[str, str]]] = {
    "hil_bench": (HilBench, {"config": "config_path"}),
    "hil_drive": (HilDrive, {"config": "drive_config", "node": "node", "eds": "eds"}),
}


def target_device(request: pytest.FixtureRequest, fixture: str
                  ) -> tuple[str, dict[str, Any]] | None:
    """The URL of the target's resource for ``fixture`` and the run options its other fields
    set; None without a labgrid environment."""
    if request.config.stash.get(LABGRID_ENV_KEY, None) is None:
        return None
    cls, options = RESOURCES[fixture]
    target = request.getfixturevalue("target")
    try:
        resource = target.get_resource(cls)
    except NoResourceFoundError:
        pytest.fail(f"{fixture}: the labgrid target {target.name} has no {cls.__name__} "
                    "resource (--lg-env)", pytrace=False)
    defaults = {option: getattr(resource, name) for name, option in options.items()
                if getattr(resource, name) not in ("", 0)}
    return resource.url, defaults
