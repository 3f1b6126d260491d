"""Exceptions raised by cpf_jax.

Every error the package raises on purpose derives from :class:`CpfJaxError`, so
a command-line driver can catch one type and print its one-line message.
Messages name the file, frame or device and say what is wrong with it.
"""

from __future__ import annotations

__all__ = [
    "CpfJaxError",
    "SourceError",
    "CameraUnavailable",
    "ViewerUnavailable",
    "OutputError",
    "MemoryTooSmall",
    "InputWarning",
    "GroundTruthWarning",
]


class CpfJaxError(Exception):
    """Base class of the errors cpf_jax raises deliberately."""


class SourceError(CpfJaxError):
    """A frame source cannot be opened or read (bad path, corrupt image, bad ground truth...)."""


class CameraUnavailable(SourceError):
    """A live camera cannot be used: its library is not installed or no device answers."""


class ViewerUnavailable(CpfJaxError):
    """A Rerun viewer to stream to cannot be reached (``RerunLogger(connect=...)``)."""


class OutputError(CpfJaxError):
    """An output file cannot be written (``RerunLogger``'s ``.rrd`` path)."""


class MemoryTooSmall(CpfJaxError):
    """A compiled filter needs more memory than the device has free (too many particles
    for the frame size): refused before it runs, not killed by the system while it does."""


class InputWarning(UserWarning):
    """An input was converted or guessed so that the run can go on (depth in metres read
    as millimetres, intrinsics assumed, depth that does not line up with the colour): the
    message says what was done and how to give the real value."""


class GroundTruthWarning(InputWarning):
    """A ground-truth file has lines that count as "target not visible" without following
    either convention for it (``0,0,0,0`` or all NaN): a negative or zero size, or one NaN
    field, which is more often a typo than a hidden target."""
