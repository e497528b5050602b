"""One exception tree for the whole library; the CLI maps it to one-line messages and exit codes."""

import importlib
from pathlib import Path
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


class RunsLostError(BimfactorError):
    """A benchmark's runs that its runner did not bring back: a Ray cluster's node or worker died on every try, or a
    process of a local pool died. `missing` holds the lost jobs' indices."""

    def __init__(self, message: str, missing: list[int] | None = None) -> None:
        super().__init__(message)
        self.missing = missing or []


def import_optional(module: str, what: str, install_hint: str) -> ModuleType:
    """Import an optional library that `what` needs, or raise DependencyError naming it with the install hint."""
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise DependencyError(f"{what} needs the Python package '{exc.name or module}': {install_hint}") from exc


def weights_problem(path: str, what: str, config_key: str, source: str) -> str | None:
    """Why the model weight file `path` cannot be used (unset, missing, a folder), in words that name the config key
    and where the file is downloaded (`source`); None when it is a file."""
    if not str(path).strip():
        return f"{what} needs a local weight file: set {config_key} (download {source})"
    resolved = Path(path).expanduser()
    if not resolved.is_file():
        kind = "is a folder, not a weights file" if resolved.is_dir() else "not found"
        return f"{what} weights file {kind}: {resolved} (from {config_key}; download {source})"
    return None


def require_weights(path: str, what: str, config_key: str, source: str) -> Path:
    """The model weight file `path` as a Path; a DependencyError of one line (`weights_problem`) otherwise."""
    problem = weights_problem(path, what, config_key, source)
    if problem is not None:
        raise DependencyError(problem)
    return Path(path).expanduser()
