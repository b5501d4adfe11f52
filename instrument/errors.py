"""The one exception family of the instrument layer.

Every failure a device can report is an :class:`InstrumentError`, itself a
:class:`scopetwin.scenes.errors.ScopetwinError`, so the command line maps all of them to
exit code 2 with a one-line message — except :class:`DeviceLost`, a device that
stopped answering mid-operation, which exits 3 (:data:`EXIT_DEVICE_LOST`). The
subclasses say *what* went wrong, independent of the world (simulated or
hardware) behind the device.
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


#: Exit status of a command whose device stopped answering mid-operation (docs/contract.md, "Command line").
EXIT_DEVICE_LOST = 3


class DeviceLost(DisconnectedError):
    """A device stopped answering mid-operation (its port gone, no answer in time, garbage, a flood).

    The message is one line: the device, why, what is known of its state ("light 'halogen' may still be on"), and
    whether every other device reached its safe state. The command line exits with :data:`EXIT_DEVICE_LOST`.

    Parameters
    ----------
    message : str
        The line described above.
    devices : sequence of str
        Names of the devices that stopped answering.
    """

    exit_status = EXIT_DEVICE_LOST

    def __init__(self, message: str, devices: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.devices = tuple(devices)

    def with_note(self, note: str) -> DeviceLost:
        """The same error with ``; note`` appended (what the command kept: frames on disk)."""
        extended = DeviceLost(f"{self}; {note}", self.devices)
        extended.__cause__ = self.__cause__
        return extended


__all__ = [
    "EXIT_DEVICE_LOST",
    "ControllerError",
    "DeviceLost",
    "DisconnectedError",
    "InstrumentError",
    "InstrumentTimeout",
    "OutOfRangeError",
    "ProtocolError",
    "RigError",
]
