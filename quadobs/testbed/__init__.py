"""The MuJoCo testbed: the vehicle model, ground truth and raw sensors (imports mujoco)."""

from .model import REQUIRED_ELEMENTS, VehicleModel, default_model_path, load_vehicle_model
from .vehicle import VehicleSim

__all__ = ["REQUIRED_ELEMENTS", "VehicleModel", "VehicleSim", "default_model_path", "load_vehicle_model"]
