"""The MuJoCo testbed: the vehicle model, ground truth and raw sensors (imports mujoco)."""

from .model import REQUIRED_ELEMENTS, VehicleModel, default_model_path, load_vehicle_model
from .vehicle import BlockStepper, VehicleSim

__all__ = ["BlockStepper", "REQUIRED_ELEMENTS", "VehicleModel", "VehicleSim", "default_model_path", "load_vehicle_model"]
