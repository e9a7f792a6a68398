"""labctl.tracking — Kalman tracking of the marker on the table plane and its prediction (paper §4.2)."""

from .models import axis_process_noise, axis_transition, plane_matrices, position_matrix
from .synthetic import SHAPES, TableTrajectory, make_trajectory, prediction_errors, sample_measurements
from .tracker import MarkerTracker, MixturePath, PredictedPath, TrackingError

__all__ = [
    "SHAPES",
    "MarkerTracker",
    "MixturePath",
    "PredictedPath",
    "TableTrajectory",
    "TrackingError",
    "axis_process_noise",
    "axis_transition",
    "make_trajectory",
    "plane_matrices",
    "prediction_errors",
    "position_matrix",
    "sample_measurements",
]
