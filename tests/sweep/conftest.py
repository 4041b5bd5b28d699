"""One local Ray per test module that asks for it (``local_ray``), shut down after the module;
``hil sweep`` joins the Ray already running in this process instead of starting its own."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="module")
def local_ray():
    from hil.sweep.engine import import_ray, start_ray

    ray = import_ray()
    start_ray(ray, workers=2, address=None)   # loopback, quiet, BLAS single-threaded
    yield ray
    ray.shutdown()
