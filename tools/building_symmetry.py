"""Diagnostic: does a rigid motion map a building's labelled objects onto objects of the same label?

A semantic localizer cannot tell two places apart when a rotation or translation of the storey carries every
object onto one of the same label (twin flats, a repeated office bay): its observations, ranges and bearings
are the same from both. For each storey of a prior this lists the non-identity rigid motions that map the most
objects within `--tolerance` metres of another object of the same label, as a rotation about a centre or a
translation, with the share of the storey's objects they carry and the share of its wall cells they carry within
0.1 m of a wall cell (`bimfactor.bim.symmetry`). Run from the repository root:

    .venv/bin/python tools/building_symmetry.py runs/bench-paper-duplex/prior
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from bimfactor.bim.symmetry import symmetries, wall_share


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("prior_dir", type=Path, help="a prior folder (bimfactor prior)")
    parser.add_argument("--tolerance", type=float, default=0.3, help="metres to an object of the same label")
    parser.add_argument("--keep", type=int, default=3, help="motions listed per storey")
    args = parser.parse_args(argv)
    from bimfactor.bim.prior import BimPrior
    from bimfactor.errors import BimfactorError

    try:
        prior = BimPrior.load(args.prior_dir)
    except (BimfactorError, OSError) as exc:
        print(f"error: {args.prior_dir} is not a readable prior folder: {exc}", file=sys.stderr)
        return 2
    for index, storey in enumerate(prior.storeys):
        objects = [o for o in prior.objects if o.storey_index == index]
        name = storey.storey.name
        motions = symmetries(
            np.array([o.position_m[:2] for o in objects]).reshape(-1, 2),
            [o.label for o in objects],
            args.tolerance,
            keep=args.keep,
        )
        print(f"storey {index} ({name}, {len(objects)} objects):")
        for motion in motions:
            print(f"  {motion.describe()}; {100 * wall_share(prior, index, motion):.0f} % of the walls onto walls")
        if not motions:
            print("  no rigid motion maps two objects onto other objects of their labels")
    return 0


if __name__ == "__main__":
    sys.exit(main())
