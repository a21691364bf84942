"""Python client for the exploration executive.

>>> from exploration_executive import Executive, MapServerMap
>>> executive = Executive("127.0.0.1:50051", token=None)
>>> area = MapServerMap.load("maps/nav2_warehouse.yaml").coarsened(0.15)
>>> mission = executive.create_mission("warehouse", area, policy="burgard")
>>> robot = executive.register_robot(mission.id, "scout", pose=(0.0, 0.0, 0.0))
>>> for assignment in robot.assignments():
...     ...

The generated messages and stubs are :mod:`exploration_executive.pb` and
:mod:`exploration_executive.rpc`.
"""

from ._proto.exploration.v1 import exploration_pb2 as pb
from ._proto.exploration.v1 import exploration_pb2_grpc as rpc
from .client import Bid, Executive, Robot, segment_labels
from .maps import FREE, OCCUPIED, UNKNOWN, MapServerMap, read_pgm
from .patches import patch_from_grid

__all__ = [
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "Bid",
    "Executive",
    "MapServerMap",
    "Robot",
    "patch_from_grid",
    "pb",
    "read_pgm",
    "rpc",
    "segment_labels",
]
