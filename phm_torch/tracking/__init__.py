"""Life tracking: a particle filter over (k, wear-rate scale s) per actuator fed by the online pipeline's
inspections, with the damage law as process model and the pipeline's calibrated k_hat error as measurement
model (``phm-track``)."""

from .builder import build_tracker
from .damage_law import DamageLaw
from .fleet import fleet_list, track_fleet
from .index import Inspection, read_index
from .particle_filter import Posterior, Tracker
from .particle_rul import ParticleRUL
from .tracker_settings import TrackerSettings

__all__ = [
    "DamageLaw",
    "Inspection",
    "ParticleRUL",
    "Posterior",
    "Tracker",
    "TrackerSettings",
    "build_tracker",
    "fleet_list",
    "read_index",
    "track_fleet",
]
