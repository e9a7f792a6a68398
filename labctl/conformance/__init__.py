"""Conformance suites: clients written from a protocol document, run against any implementation.

:mod:`labctl.conformance.robot` checks a robot controller against docs/protocols/robot.md
(``labctl robot conformance``); :mod:`labctl.conformance.bridge_example` is the bridge skeleton a
lab starts from.
"""
