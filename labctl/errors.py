"""Exceptions that the CLI turns into one-line messages and exit codes."""

from __future__ import annotations


class LabctlError(Exception):
    """Base of labctl's expected failures. ``exit_code`` is what the CLI exits with."""

    exit_code = 1


class UserInputError(LabctlError):
    """Bad input from the user (a file, an option, a value): exit status 2."""

    exit_code = 2


class DeviceError(LabctlError):
    """A device did not answer, answered wrongly, or reported a fault: exit status 3."""

    exit_code = 3


class MotionRefused(DeviceError):
    """A controller refused a motion it was sent, before moving (nothing moved): the planner may try another."""
