"""The labgrid resources of hil: where a relay bench or a CiA 402 drive is, and the config
that describes it. Plain :class:`labgrid.resource.Resource` s: the device's URL already names
its host, so an exporter publishes them as they are written (it forwards a class it does not
know as a plain entry) and a client makes them again with these classes."""

from __future__ import annotations

import attr
from labgrid.factory import target_factory
from labgrid.resource import Resource

_text = attr.validators.instance_of(str)


@target_factory.reg_resource
@attr.s(eq=False)
class HilBench(Resource):
    """A relay bench. ``url``: ``modbus-tcp://HOST:PORT`` or ``modbus-rtu:///dev/X``;
    ``config``: its bench.toml (a path on the machine that runs hil; "" = hil's packaged
    one)."""

    url = attr.ib(validator=_text)
    config = attr.ib(default="", validator=_text)


@target_factory.reg_resource
@attr.s(eq=False)
class HilDrive(Resource):
    """A CiA 402 drive. ``url``: ``socketcand://HOST:PORT[/CHANNEL]`` or any python-can
    interface (``socketcan://can0``...); ``node``: its CANopen node id (0 = drive.toml's
    ``[master] node_id``); ``eds``: its EDS ("" = drive.toml's); ``config``: its drive.toml
    ("" = hil's packaged one). Paths are read on the machine that runs hil."""

    url = attr.ib(validator=_text)
    node = attr.ib(default=0, validator=attr.validators.instance_of(int))
    eds = attr.ib(default="", validator=_text)
    config = attr.ib(default="", validator=_text)
