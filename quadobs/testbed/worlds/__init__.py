"""The worlds of the testbed: truth and raw sensor readings a block of steps at a time (imports mujoco).

:class:`~quadobs.testbed.worlds.base.World` is the interface; the MuJoCo point-mass vehicle
(:class:`PointMassWorld`) is the first world.
"""

from quadobs.testbed.worlds.base import Columns, World
from quadobs.testbed.worlds.model import (
    REQUIRED_ELEMENTS,
    VehicleModel,
    default_model_path,
    load_vehicle_model,
)
from quadobs.testbed.worlds.point_mass import BlockStepper, PointMassWorld, VehicleSim

__all__ = [
    "REQUIRED_ELEMENTS",
    "BlockStepper",
    "Columns",
    "PointMassWorld",
    "VehicleModel",
    "VehicleSim",
    "World",
    "default_model_path",
    "load_vehicle_model",
]
