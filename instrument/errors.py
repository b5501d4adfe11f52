"""The one exception family of the instrument layer.

Every failure a device can report is an :class:`InstrumentError`, itself a
:class:`scopetwin.scenes.errors.ScopetwinError`, so the command line maps all of them to
exit code 2 with a one-line message. The four subclasses say *what* went
wrong, independent of the world (simulated or hardware) behind the device.
"""

from __future__ import annotations

from scopetwin.scenes.errors import ScopetwinError


class InstrumentError(ScopetwinError):
    """A device refused, failed or could not be reached; the message names the device."""


class InstrumentTimeout(InstrumentError, TimeoutError):
    """No (complete) answer arrived within the configured timeout."""


class OutOfRangeError(InstrumentError, ValueError):
    """A requested value lies outside the device's limits (raised before any I/O)."""


class ProtocolError(InstrumentError):
    """An answer that does not follow the wire protocol, or an error code reported by the device."""


class ControllerError(ProtocolError):
    """The controller reported an error code (PI ``ERR?``, jena ``err,N``, FPGA error frame).

    Parameters
    ----------
    message : str
        What failed, naming the device and the command.
    code : int
        The controller's numeric error code.
    """

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


class DisconnectedError(InstrumentError, ConnectionError):
    """The transport is closed, gone, or the line dropped."""


class RigError(InstrumentError, ValueError):
    """A rig file that cannot be loaded (unknown driver, missing field, bad limit)."""


__all__ = [
    "ControllerError",
    "DisconnectedError",
    "InstrumentError",
    "InstrumentTimeout",
    "OutOfRangeError",
    "ProtocolError",
    "RigError",
]
