"""Error types raised on purpose by plenoctree.

Every error a user can cause (bad file, bad option, missing backend) is one of these, with a
message of the form ``"<file>: <problem>"`` when a file is involved.
"""

__all__ = ["PlenOctreeError", "DatasetError", "TreeFormatError", "BackendError", "ConfigError"]


class PlenOctreeError(Exception):
    """Base class of every error plenoctree raises on purpose."""


class DatasetError(PlenOctreeError, ValueError):
    """A dataset folder or one of its files is missing, unreadable or inconsistent."""


class TreeFormatError(PlenOctreeError, ValueError):
    """A tree file (native, svox or compressed) is missing keys, malformed or inconsistent."""


class BackendError(PlenOctreeError, RuntimeError):
    """A requested compute backend is missing or unusable on this machine."""


class ConfigError(PlenOctreeError, ValueError):
    """An option or configuration value is out of range or inconsistent."""
