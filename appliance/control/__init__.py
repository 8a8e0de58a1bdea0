"""EMA control: what the appliance knows about its coils and what it decides each frame.

``load_coils`` -> ``ActuationModel`` (field and gradient per ampere at a point) -> ``CurrentAllocator``
(minimum-norm currents within limits, scaled as a whole when unreachable); ``PathFollower`` turns the
tracked posture into the field and force to request; ``SafetySupervisor`` holds, zeroes or stops.
"""
from __future__ import annotations

from appliance.control.actuation import ActuationModel
from appliance.control.allocation import Allocation, CurrentAllocator
from appliance.control.coils_config import CoilsConfig, load_coils
from appliance.control.path_follower import Command, FollowerSettings, PathFollower, load_path
from appliance.control.safety import Decision, Mode, SafetySettings, SafetySupervisor

__all__ = [
    "ActuationModel", "Allocation", "CoilsConfig", "Command", "CurrentAllocator", "Decision",
    "FollowerSettings", "Mode", "PathFollower", "SafetySettings", "SafetySupervisor", "load_coils", "load_path",
]
