"""Diagnostic: when the localizer is ready to suggest where to look, is the truth among the places it would tell apart?

Runs each standard route of a prior's building passively (the benchmark's routes, seed and defaults, variant
smcl+graph) and asks `Localizer.suggest()` after every keyframe without following it. Over the keyframes where a goal
comes back (the belief is a few places and none holds it), it counts those where the true pose lies within
`active.suggest.SAME_PLACE_M` of a place on its storey, and the mean probability of that place against the most
probable one's. A truth outside every place is one that views chosen to tell the places apart cannot find
(docs/active.md). Run from the repository root:

    .venv/bin/bimfactor prior ../shared/data/ifc/AC11-Institute-Var-2-IFC.ifc -o runs/prior/ac11
    .venv/bin/python tools/truth_among_modes.py runs/prior/ac11
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("prior_dir", type=Path, help="a prior folder (bimfactor prior)")
    parser.add_argument("--routes", type=int, default=6, help="routes 0..N-1 (repeat 0 of each)")
    args = parser.parse_args(argv)
    from threadpoolctl import threadpool_limits

    from bimfactor.active.suggest import SAME_PLACE_M
    from bimfactor.bim.symmetry import twin_motions
    from bimfactor.config import load_config
    from bimfactor.evaluation.paper import run_seed, simulate_routes
    from bimfactor.pipeline import Localizer, scan_matcher

    cfg = load_config("default", ["localization.variant=smcl+graph"])
    asked, among, truth_p, top_p = 0, 0, [], []
    with threadpool_limits(1):  # as the benchmark's runs: one BLAS thread
        routes = [(route, cfg.evaluation.trajectory_length) for route in range(args.routes)]
        sims, prior = simulate_routes(args.prior_dir, cfg, routes)
        twins, matcher = twin_motions(prior), scan_matcher(prior, cfg)
        for route, sim in enumerate(sims):
            seed = run_seed(cfg.seed, route, 0)
            localizer = Localizer(prior, sim.meta, cfg, seed, matcher=matcher, twins=twins)
            for frame in sim.frames:
                localizer.step(frame)
                suggestion = localizer.suggest()
                if suggestion.goal_odom is None:
                    continue
                near = [
                    h.probability
                    for h in suggestion.hypotheses
                    if h.storey == frame.gt_storey and np.hypot(*(h.pose[:2] - frame.gt_pose[:2])) < SAME_PLACE_M
                ]
                asked += 1
                among += bool(near)
                truth_p.append(sum(near))
                top_p.append(suggestion.hypotheses[0].probability)
    if not asked:
        print(f"{args.prior_dir}: no keyframe of {args.routes} routes had a suggestion")
        return 0
    print(
        f"{args.prior_dir}: {asked} keyframes with a suggestion over {args.routes} routes; the truth among the places "
        f"in {among / asked:.0%}; its probability {np.mean(truth_p):.2f} on average, the most probable place's "
        f"{np.mean(top_p):.2f}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
