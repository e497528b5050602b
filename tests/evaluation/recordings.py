"""Reading Rerun recordings back in tests, with rerun-sdk's own RRD reader (the viz extra)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

from bimfactor.evaluation.viewer import TIMELINE

STATIC = "static"


def logged(path: Path) -> dict[str, set]:
    """Entity path (without the leading /) → the keyframes it was logged at, or {"static"} for static data; a clear
    (`rr.Clear`) is not data."""
    from rerun.chunk import RrdReader

    found: dict[str, set] = defaultdict(set)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        if any(name.startswith("Clear:") for name in batch.schema.names):
            continue
        steps = batch.column(TIMELINE).to_pylist() if TIMELINE in batch.schema.names else [STATIC]
        found[chunk.entity_path.lstrip("/")].update(steps)
    return found
