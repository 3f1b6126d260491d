"""Exceptions raised by cpf_jax.

Every error the package raises on purpose derives from :class:`CpfJaxError`, so
a command-line driver can catch one type and print its one-line message.
Messages name the file, frame or device and say what is wrong with it.
"""

from __future__ import annotations

__all__ = ["CpfJaxError", "SourceError", "CameraUnavailable", "ViewerUnavailable", "OutputError"]


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
