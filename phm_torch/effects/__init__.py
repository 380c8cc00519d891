"""Library of optional physical effects; importing it registers every built-in effect."""

from .aero_hinge_load import AeroHingeLoad
from .base import EFFECTS, Effect, EffectContext, EffectParam, build_effects, register_effect, sized_defaults
from .cogging_torque import CoggingTorque
from .inverter_dead_time import InverterDeadTime
from .position_sensor_lag import PositionSensorLag
from .stribeck_friction import StribeckFriction
from .torque_constant_saturation import TorqueConstantSaturation
from .torque_ripple import TorqueRipple
from .transmission_compliance import TransmissionCompliance
from .viscous_friction import ViscousFriction
from .winding_temperature import WindingTemperature

__all__ = [
    "EFFECTS",
    "AeroHingeLoad",
    "CoggingTorque",
    "Effect",
    "EffectContext",
    "EffectParam",
    "InverterDeadTime",
    "PositionSensorLag",
    "StribeckFriction",
    "TorqueConstantSaturation",
    "TorqueRipple",
    "TransmissionCompliance",
    "ViscousFriction",
    "WindingTemperature",
    "build_effects",
    "register_effect",
    "sized_defaults",
]
