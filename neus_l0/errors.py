"""User-facing errors.

Anything the user can fix (bad input files, bad configs, bad arguments) raises
`NeusL0Error` with one line that names the file and what is wrong. The CLI prints that
line and exits with status 2 instead of showing a traceback.
"""


class NeusL0Error(Exception):
    """An error caused by the user's input, reported as one clear line."""


class SceneError(NeusL0Error):
    """A scene folder (images, masks, cameras) is missing, malformed or inconsistent."""


class ConfigError(NeusL0Error):
    """A configuration file or override is invalid."""


class OutputError(NeusL0Error, OSError):
    """An output cannot be written (no permission, a file in the way, a full disk). Also an
    `OSError`, so that code catching those still does."""
