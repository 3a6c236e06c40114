"""The sensor agent's own exceptions; the CLI prints them as one red line and exits 1."""


class AgentError(Exception):
    """A known problem, explained in one line (bad config, missing BlueZ, no acknowledgement)."""


class ConfigError(AgentError):
    """A malformed agent configuration; the message names the file and the field."""


class BackendError(AgentError):
    """A scanner backend that cannot start or run (no adapter, BlueZ missing, bad replay file)."""


class AckTimeout(AgentError):
    """The collector did not acknowledge everything the agent published within the bound."""
