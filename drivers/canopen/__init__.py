"""A CiA 402 master on CANopen, split along the CiA 301 services as canopen's node is: the SDO
client (:mod:`.sdo`), NMT and heartbeats (:mod:`.nmt`), PDO configuration (:mod:`.pdo`), the
cyclic exchange (:mod:`.cyclic`, the hot path), CiA 402 state control (:mod:`.state`), the
drive's scaling (:mod:`.scaling`) and description (:mod:`.eds`), and the master that composes
them (:mod:`.master`). :mod:`.bus` opens any python-can interface from a URL; :mod:`.scan`
looks at the nodes of a bus without changing anything."""

from hil.drivers.canopen.bus import CanBusSpec, open_can_bus, parse_can_url
from hil.drivers.canopen.config import DriveMasterConfig
from hil.drivers.canopen.cyclic import Feedback, LinkStats
from hil.drivers.canopen.errors import (
    BusSharedError,
    DriveError,
    DriveFaultError,
    DriveLinkLostError,
    DriveStateError,
)
from hil.drivers.canopen.link import CanLink
from hil.drivers.canopen.master import CanDriveMaster
from hil.protocols.cia301 import SdoAbortError

__all__ = ["BusSharedError", "CanBusSpec", "CanDriveMaster", "CanLink", "DriveError",
           "DriveFaultError", "DriveLinkLostError", "DriveMasterConfig", "DriveStateError",
           "Feedback", "LinkStats", "SdoAbortError", "open_can_bus", "parse_can_url"]
