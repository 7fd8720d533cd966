"""The MuJoCo testbed: the vehicle model, ground truth and raw sensors (imports mujoco)."""

from quadobs.testbed.worlds.model import REQUIRED_ELEMENTS, VehicleModel, default_model_path, load_vehicle_model
from quadobs.testbed.worlds.point_mass import BlockStepper, VehicleSim

__all__ = ["BlockStepper", "REQUIRED_ELEMENTS", "VehicleModel", "VehicleSim", "default_model_path", "load_vehicle_model"]
