"""The annotator's own exceptions; the CLI turns them into one-line messages and exit code 1."""


class AnnotatorError(Exception):
    """A problem with the user's input or data, explained in one line."""


class ConfigError(AnnotatorError):
    """A malformed or inconsistent experiment / rig / calibration file."""


class NoDataError(AnnotatorError):
    """Nothing to work with: no markers detected, no RSSI rows, no sync event found."""


class DemoError(AnnotatorError):
    """A step of the demo failed; the message says which and why."""
