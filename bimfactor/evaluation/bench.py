"""Where the benchmarks (`bimfactor bench ...`) find the shared data beside the project: the real IFC buildings and
the real RGB-D recordings."""

from __future__ import annotations

import logging
from pathlib import Path

from bimfactor.errors import InputError

log = logging.getLogger(__name__)

PROJECT_ROOT = Path(__file__).resolve().parents[2]
SHARED_IFC_DIR = PROJECT_ROOT.parent / "shared" / "data" / "ifc"
SHARED_REAL_DIR = PROJECT_ROOT.parent / "shared" / "data" / "real"
"""Real RGB-D recordings with camera poses (TUM folders) beside the project: the detector's and the scene graph's
real-frame checks."""


def find_shared_ifc_dir() -> Path | None:
    """The real IFC buildings in `../shared/data/ifc` beside the project root, or None when absent."""
    return SHARED_IFC_DIR if SHARED_IFC_DIR.is_dir() else None


def shared_ifc_dir() -> Path:
    """Like `find_shared_ifc_dir`, but a missing folder is an InputError that says where it was expected."""
    found = find_shared_ifc_dir()
    if found is None:
        raise InputError(
            f"the real IFC buildings are not there: expected the folder {SHARED_IFC_DIR} "
            "(../shared/data/ifc beside the project); pass IFC files with --ifc instead"
        )
    return found
