"""Registration tests reuse the simulator's session fixtures (the paper-floor prior and its IFC model)."""

from __future__ import annotations

from tests.sim.conftest import paper_floor, text_embedder  # noqa: F401  (fixtures, re-exported)
