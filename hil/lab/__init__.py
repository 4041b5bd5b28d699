"""hil's benches and drives as labgrid resources, for labs that share them: several benches
and drives, more people and CI runners than benches. Needs ``pip install 'hil[lab]'``.

* :mod:`hil.lab.resources` - the resources ``HilBench`` (a relay bench: its Modbus URL, its
  bench.toml) and ``HilDrive`` (a CiA 402 drive: its CAN URL, node, EDS, drive.toml),
  registered with labgrid's target factory; an exporter publishes them, a place groups them;
* :mod:`hil.lab.drivers` - ``HilBenchDriver`` and ``HilDriveDriver``: the bench or drive of
  a target, opened through hil's safety layer while the driver is active;
* :mod:`hil.lab.place` - a place held for one run (acquired unless already yours, waited for
  through a labgrid reservation, released after the safe stop);
* :mod:`hil.lab.pytest_target` - the ``hil_bench`` / ``hil_drive`` fixtures on a labgrid
  target (``pytest --lg-env``);
* :mod:`hil.lab.local` - a coordinator and an exporter on 127.0.0.1 (tests, benchmarks, trying
  it on one machine).

``--place`` / ``--coordinator`` / ``--wait`` of ``hil bench run`` and ``hil servo run`` are
:mod:`hil.cli.place`.

An environment YAML names ``hil.lab`` under ``imports:``; importing it registers the
resources and drivers (and imports labgrid).
"""

from hil.lab.drivers import HilBenchDriver, HilDriveDriver
from hil.lab.resources import HilBench, HilDrive

__all__ = ["HilBench", "HilBenchDriver", "HilDrive", "HilDriveDriver"]
