"""labctl.tracking — Kalman tracking of the marker on the table plane and its prediction (paper §4.2)."""

from .models import axis_process_noise, axis_transition, plane_matrices, position_matrix
from .tracker import MarkerTracker, MixturePath, PredictedPath, TrackingError

__all__ = [
    "MarkerTracker",
    "MixturePath",
    "PredictedPath",
    "TrackingError",
    "axis_process_noise",
    "axis_transition",
    "plane_matrices",
    "position_matrix",
]
