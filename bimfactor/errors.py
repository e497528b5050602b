"""One exception tree for the whole library; the CLI maps it to one-line messages and exit codes."""

import importlib
from types import ModuleType


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


def import_optional(module: str, what: str, install_hint: str) -> ModuleType:
    """Import an optional library that `what` needs, or raise DependencyError naming it with the install hint."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DependencyError(f"{what} needs the Python package '{exc.name or module}': {install_hint}") from exc
