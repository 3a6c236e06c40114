"""The collector's own exceptions; the CLI turns them into one-line messages and exit code 1."""


class CollectorError(Exception):
    """A problem the user can fix, explained in one line."""


class ConfigError(CollectorError):
    """A malformed collector.yaml or an inconsistent set of options."""


class Unreachable(CollectorError):
    """No collector answered on the control keys."""


class CommandFailed(CollectorError):
    """The collector answered a control request with an error (e.g. a run is already active)."""
