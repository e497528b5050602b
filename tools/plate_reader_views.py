"""Door plates read by `PlateReader` (where a plate can be) against RapidOCR on whole frames, over views of every
plate the simulator hangs in a prior's building.

The simulated camera stands 1.0, 1.8 and 2.5 m in front of each plate, 0.4 m to either side, facing it (a view counts
when 30 or more of the plate's pixels are in the image); each reader reads every view, with no belief (any column).
A view is read right when the plate's text is among the texts read; every other text is a wrong read. Prints one line
per reader: right, wrong, median and mean milliseconds per view. Run from the repository root:

    .venv/bin/bimfactor prior ../shared/data/ifc/AC11-Institute-Var-2-IFC.ifc -o runs/prior/ac11
    .venv/bin/python tools/plate_reader_views.py runs/prior/ac11
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bimfactor.config import load_config
from bimfactor.localization.measurements.text import normalise_text
from bimfactor.perception.ocr import PlateReader, RapidOcrReader
from bimfactor.sim.sensors import RgbdCamera
from bimfactor.sim.simulate import build_world, load_world_inputs
from bimfactor.types import Frame

DISTANCES_M = (1.0, 1.8, 2.5)
SIDES_M = (-0.4, 0.4)
MIN_PLATE_PX = 30


def plate_views(prior_dir: str, seed: int = 0) -> tuple[list[tuple[str, Frame]], RgbdCamera]:
    """(text, frame) of every view of every hung plate, and the camera."""
    cfg = load_config("default")
    prior, model = load_world_inputs(prior_dir, cfg)
    world = build_world(prior, model, cfg, seed)
    camera = RgbdCamera.from_config(world, cfg)
    rng = np.random.default_rng(seed)
    views = []
    for plate in (r for r in world.instances if r.get("text")):
        face, right = np.array(plate["plate_face_m"]), np.array(plate["plate_right_xy"])
        elevation = prior.storeys[plate["storey_index"]].storey.elevation_m
        for distance in DISTANCES_M:
            for side in SIDES_M:
                for out in (1.0, -1.0):  # the plate's front is on one side of its wall: the other view shows none
                    xy = face[:2] + out * np.array([right[1], -right[0]]) * distance + right * side
                    yaw = np.arctan2(face[1] - xy[1], face[0] - xy[0])
                    T = np.eye(4)
                    T[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
                    T[:3, 3] = [xy[0], xy[1], elevation]
                    image = camera.render(T, elevation, rng)
                    if (image.instance_ids == plate["id"]).sum() < MIN_PLATE_PX:
                        continue
                    depth = np.nan_to_num(image.depth_m)
                    views.append((plate["text"], Frame(len(views), 0.0, image.rgb, depth, np.zeros(3))))
    return views, camera


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("prior_dir", help="a prior folder (bimfactor prior) whose IFC file is where it says")
    args = parser.parse_args(argv)
    views, camera = plate_views(args.prior_dir)
    print(f"{len(views)} views")
    readers = {
        "where plates can be": PlateReader(camera.intrinsics, camera.T_base_camera),
        "whole frames": RapidOcrReader(),
    }
    for name, reader in readers.items():
        right = wrong = 0
        times = []
        for text, frame in views:
            started = time.perf_counter()
            read = {normalise_text(r.text) for r in reader.read(frame)}
            times.append((time.perf_counter() - started) * 1000)
            right += normalise_text(text) in read
            wrong += len(read - {normalise_text(text)})
        print(f"{name}: {right} right, {wrong} wrong, {np.median(times):.1f} ms median, {np.mean(times):.1f} ms mean")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
