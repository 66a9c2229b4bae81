"""Exception types that carry a clear, user-facing message."""


class PointGTError(Exception):
    """Base class: the message is meant for the user and names the file and the problem."""


class DataError(PointGTError):
    """A dataset on disk is missing files or holds invalid content."""


class ModelFileError(PointGTError):
    """A .pgt model file is missing, truncated, corrupt or of an unsupported version."""


class InputError(PointGTError):
    """Arrays handed to the core (points, ids, atlas images) have the wrong shape, dtype or values."""
