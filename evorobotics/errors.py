"""Exceptions of the science package.

Hierarchy:
    EvoError                 root; catch this to handle any failure of `evorobotics`
    ├── ControllerDocumentError   a controller document is malformed, non-finite or tampered
    └── MazeError                 a maze file or grid is malformed (names the line)

Bad arguments to functions raise plain `ValueError`.
"""


class EvoError(Exception):
    """Root of every error raised by `evorobotics`."""


class ControllerDocumentError(EvoError):
    """A controller document cannot be trusted: wrong shape, NaN/inf, or a bad sha256."""


class MazeError(EvoError):
    """A maze cannot be built: malformed text (the message names the line) or bad grid."""
