"""How `swarmdrop agent` ends: its exit codes (docs/companion.md) and the failure that carries one.

Set-up, launch and supervision raise NodeFailure; AgentNode.run turns it into the exit
code. They live here, apart from the runner, so that every module of the node can raise
them without importing the runner.
"""
from __future__ import annotations

from enum import IntEnum


class ExitCode(IntEnum):
    """Exit status of `swarmdrop agent` (AgentNode.run's result; NodeFailure carries one):
    what went wrong, so that the fleet harness and a supervisor can tell causes apart."""

    OK = 0
    """Stopped by SIGINT/SIGTERM (the normal end of a flight)."""
    ERROR = 1
    """An unexpected internal error (logged with its traceback)."""
    CONFIG = 2
    """Bad arguments or mission file."""
    NO_AUTOPILOT = 3
    """No autopilot HEARTBEAT within the timeout, or an autopilot of no known dialect."""
    SETUP = 4
    """Streams, clock, EKF origin or parameters could not be set up in time."""
    LAUNCH = 5
    """Arming, take-off or the switch to offboard/GUIDED was refused after retries."""
    LINK_LOST = 6
    """The autopilot fell silent in flight (its own failsafe flies the vehicle)."""
    IDENTITY = 7
    """Only autopilots of another sysid than the mission assigns to --vehicle-id were heard
    (no --target-sysid override): refused before anything was commanded."""


class NodeFailure(RuntimeError):
    """The node cannot go on; `code` is the process's exit code, the message says why
    (AgentNode.run logs it at ERROR)."""

    def __init__(self, code: ExitCode, message: str):
        super().__init__(message)
        self.code = code
