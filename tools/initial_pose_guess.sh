#!/usr/bin/env bash
# Localize the six standard trajectories of a prior's building twice per variant: from the uniform start, and
# from an initial pose guess (--initial-pose) offset from the first frame's ground truth; prints one line per run.
#
#   bash tools/initial_pose_guess.sh PRIOR_DIR OUT_DIR [DX_M DY_M DYAW_DEG]     (default offset 0.7 -0.7 20: 1 m, 20°)
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."
prior="${1:?usage: tools/initial_pose_guess.sh PRIOR_DIR OUT_DIR [DX_M DY_M DYAW_DEG]}"
out="${2:?usage: tools/initial_pose_guess.sh PRIOR_DIR OUT_DIR [DX_M DY_M DYAW_DEG]}"
dx="${3:-0.7}" dy="${4:--0.7}" dyaw="${5:-20}"
bimfactor=.venv/bin/bimfactor
mkdir -p "$out"
for k in 0 1 2 3 4 5; do
    "$bimfactor" simulate "$prior" -o "$out/seq$k" --trajectory "$k" >/dev/null
    guess=$(.venv/bin/python -c "
import numpy as np
from bimfactor.io.sequence import read_sequence
x, y, yaw = read_sequence('$out/seq$k')[0].gt_pose
print(f'{x + $dx},{y + $dy},{np.degrees(yaw) + $dyaw}')")
    for variant in smcl smcl+graph; do
        echo "trajectory $k $variant uniform: $("$bimfactor" localize "$prior" "$out/seq$k" -o "$out/uniform-$variant-$k" \
            --variant "$variant" | tail -1)"
        echo "trajectory $k $variant guess:   $("$bimfactor" localize "$prior" "$out/seq$k" -o "$out/guess-$variant-$k" \
            --variant "$variant" --initial-pose "$guess" | tail -1)"
    done
done
