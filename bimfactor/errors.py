"""One exception tree for the whole library; the CLI maps it to one-line messages and exit codes."""


class BimfactorError(Exception):
    """Base of every error bimfactor raises on purpose."""

    exit_code = 1


class InputError(BimfactorError):
    """Bad user input: a missing, unreadable, corrupt or unsupported file."""

    exit_code = 2


class IfcError(InputError):
    """An IFC file that cannot be used: not IFC, truncated, unsupported schema, no walls."""


class ConfigError(InputError):
    """A configuration that does not validate: unknown key, wrong type, bad value."""


class FormatError(InputError):
    """A bimfactor on-disk artefact (prior, sequence) that is missing parts or has another version."""


class DependencyError(BimfactorError):
    """An optional dependency or model weight file that this code path needs is missing."""

    exit_code = 3
