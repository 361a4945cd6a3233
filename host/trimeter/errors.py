"""Exceptions shared by every layer; the CLI turns a TrimeterError into one clear line and exit code 2."""


class TrimeterError(Exception):
    """Base class for errors a user can act on (bad input, bad file, device refused)."""


class InputError(TrimeterError, ValueError):
    """An impossible value in a recipe, a command line or a data file. The message names the field."""


class MapFileError(TrimeterError):
    """A map or map-table file that is truncated, tampered with, or of an unknown version."""


class OutputError(TrimeterError):
    """A file or directory that cannot be written (full disk, read-only, no permission). The message names it."""


class DeviceError(TrimeterError):
    """The instrument did not answer, answered wrongly, or refused (firmware/register-map mismatch)."""


class CheckError(TrimeterError):
    """A check refused a calibration or a measurement (a sample in the holder at calibration, a lamp that
    failed since): nothing was saved as one. The message says what was seen and what to do."""


class BuildError(TrimeterError):
    """A map build that stopped: a column failed on every attempt, or the cluster could not be used. The
    message names the column and where the finished ones are kept."""
