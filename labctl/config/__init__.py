"""Configuration: the lab workspace (``lab.yaml``) and its driver files, as typed objects."""

from .devices import CameraConfig, HostLinkConfig, LensConfig, RobotConfig, TableConfig
from .lab import Lab, LabConfig, load_lab
from .schema import ConfigError, from_mapping, read_yaml, to_plain

__all__ = [
    "CameraConfig",
    "ConfigError",
    "HostLinkConfig",
    "Lab",
    "LabConfig",
    "LensConfig",
    "RobotConfig",
    "TableConfig",
    "from_mapping",
    "load_lab",
    "read_yaml",
    "to_plain",
]
