"""Benchmark: how well RapidOCR reads the simulator's door plates, against what the sim text reader assumes.

The simulated world prints each plate's room number on its face (`sim.world.PlateTexture`), so the real OCR engine
can read rendered frames. This places the camera in front of every plate of a building at several distances and
viewing angles, renders the frame (no image noise), and runs `perception.ocr.RapidOcrReader` on it and the
`perception.text.SimTextReader` (its legibility test alone: read probability 1, no character errors). Per bin of
the plate's height in the image it prints how often RapidOCR reads the plate's text exactly, how often it reads
something within one character of it, its character error rate over the plates it reads, and how often the sim
reader calls the plate legible. Over the views the sim reader calls legible it then fits the sim reader's error
model (`perception.text.sim_*`): how often RapidOCR reads anything, and per character of its best reading how often
it reads a look-alike, another character, or nothing. Writes `results.json` and `read_rate.png` to `-o`. Run from
the repository root:

    .venv/bin/python tools/calibrate_text_reader.py runs/bench-paper-duplex/prior ../shared/data/ifc/duplex.ifc \\
        -o runs/ocr-calibration
    (add --set sim.camera.width=640 --set sim.camera.height=480 for a 640 × 480 camera)
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

DISTANCES_M = (1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
ANGLES_DEG = (0.0, 30.0, 50.0)
HEIGHT_BINS_PX = (0, 6, 8, 10, 12, 15, 20, 30, 1000)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("prior_dir", type=Path, help="a prior folder built with room numbers (bimfactor prior)")
    parser.add_argument("ifc", type=Path, help="the IFC file the prior was built from")
    parser.add_argument("-o", "--out", type=Path, required=True, help="output folder")
    parser.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    args = parser.parse_args(argv)
    from bimfactor.errors import BimfactorError

    try:
        rows, meta = _measure(args.prior_dir, args.ifc, args.overrides)
    except (BimfactorError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    table = _table(rows)
    print(f"{meta['frames']} frames of {meta['plates']} plates at {meta['camera']}; RapidOCR {meta['ocr_ms']:.0f} ms")
    print(f"{'plate px':>10} {'frames':>7} {'exact %':>8} {'≤1 edit %':>10} {'CER %':>6} {'sim legible %':>14}")
    for row in table:
        cer = "-" if row["cer"] is None else f"{100 * row['cer']:.1f}"
        print(
            f"{row['bin']:>10} {row['frames']:>7} {100 * row['exact']:>8.0f} {100 * row['near']:>10.0f} {cer:>6} "
            f"{100 * row['sim_legible']:>14.0f}"
        )
    fit = _reader_model(rows)
    print(
        f"sim reader fit over {fit['legible_views']} legible views ({100 * fit['read_share']:.0f} % read): "
        f"sim_read_probability {fit['read_probability']:.2f}, sim_read_char_px {fit['read_char_px']:.2f}, "
        f"sim_read_char_scale_px {fit['read_char_scale_px']:.2f}, "
        f"sim_look_alike_rate {fit['look_alike_rate']:.3f}, sim_char_error_rate {fit['char_error_rate']:.3f}, "
        f"sim_drop_rate {fit['drop_rate']:.3f} (characters inserted: {fit['insert_rate']:.3f}, not simulated)"
    )
    args.out.mkdir(parents=True, exist_ok=True)
    out = {**meta, "bins": table, "reader_model": fit, "frames_read": rows}
    (args.out / "results.json").write_text(json.dumps(out, indent=1))
    _plot(table, meta, args.out / "read_rate.png")
    print(f"results: {args.out / 'results.json'}\nfigure: {args.out / 'read_rate.png'}")
    return 0


def _measure(prior_dir: Path, ifc: Path, overrides: list[str]) -> tuple[list[dict], dict]:
    from bimfactor.bim.ifc import load_ifc
    from bimfactor.bim.plates import normalise_text
    from bimfactor.bim.prior import BimPrior
    from bimfactor.config import load_config
    from bimfactor.errors import InputError
    from bimfactor.localization.measurements.text import edit_distance
    from bimfactor.perception.ocr import RapidOcrReader
    from bimfactor.perception.text import SimTextReader
    from bimfactor.progress import progress
    from bimfactor.sim.sensors import RgbdCamera
    from bimfactor.sim.simulate import build_world
    from bimfactor.types import Frame, SequenceMeta

    cfg = load_config(None, [*overrides, "sim.door_plates.enabled=true", "perception.text.sim_read_probability=1",
                             "perception.text.sim_read_char_px=0", "perception.text.sim_read_char_scale_px=0.001",
                             "perception.text.sim_look_alike_rate=0", "perception.text.sim_char_error_rate=0",
                             "perception.text.sim_drop_rate=0"])  # fmt: skip
    prior = BimPrior.load(prior_dir)
    world = build_world(prior, load_ifc(ifc, cfg.bim.ifc), cfg, seed=0)
    if not world.textures:
        raise InputError(f"{prior_dir} has no door plates: rebuild the prior with `bimfactor prior` (room numbers)")
    camera = RgbdCamera(world, cfg.sim.camera, cfg.sensor.depth_noise, cfg.sim.depth_dropout, 0.0)
    meta = SequenceMeta("plates", "sim", camera.intrinsics, camera.T_base_camera, instances=world.instances)
    sim_reader = SimTextReader(meta, cfg.perception.text, np.random.default_rng(0))
    ocr = RapidOcrReader(cfg.perception.text.min_score)
    views = [(rec, d, a) for rec in world.instances if "plate_face_m" in rec for d in DISTANCES_M for a in ANGLES_DEG]
    rows, times = [], []
    for rec, distance, angle in progress(views, desc="plate views", unit="frame"):
        face, right = np.asarray(rec["plate_face_m"]), np.asarray(rec["plate_right_xy"])
        normal = np.array([right[1], -right[0]])  # out of the wall, towards the reader
        c, s = np.cos(np.deg2rad(angle)), np.sin(np.deg2rad(angle))
        look = c * normal + s * right  # from the plate to the camera
        xy = face[:2] + distance * look
        pose = np.array([*xy, np.arctan2(-look[1], -look[0])])
        elevation = prior.storeys[rec["storey_index"]].storey.elevation_m
        image = camera.render(pose, elevation)
        rows_px, cols_px = np.nonzero(image.instance_ids == rec["id"])
        if not len(rows_px):
            continue  # out of view (above the camera's field, or hidden)
        frame = Frame(0, 0.0, image.rgb, image.depth_m, np.zeros(3), instance_ids=image.instance_ids)
        started = time.perf_counter()
        readings = ocr.read(frame)
        times.append((time.perf_counter() - started) * 1000)
        truth = normalise_text(rec["text"])
        read = [normalise_text(r.text) for r in readings]
        edits = min((edit_distance(t, truth) for t in read if t), default=None)
        rows.append(
            {
                "text": truth,
                "distance_m": distance,
                "angle_deg": angle,
                "plate_height_px": int(rows_px.max() - rows_px.min() + 1),
                "plate_width_px": int(cols_px.max() - cols_px.min() + 1),
                "read": read,
                "edits": edits,
                "sim_legible": any(r.gt_instance_id == rec["id"] for r in sim_reader.read(frame)),
            }
        )
    k = camera.intrinsics
    return rows, {
        "plates": len(world.textures),
        "frames": len(rows),
        "camera": f"{k.width} × {k.height} px, {cfg.sim.camera.hfov_deg:.0f}° wide",
        "ocr_ms": statistics.median(times) if times else float("nan"),
        "sim_min_height_px": cfg.perception.text.sim_min_height_px,
        "distances_m": list(DISTANCES_M),
        "angles_deg": list(ANGLES_DEG),
    }


def _table(rows: list[dict]) -> list[dict]:
    """Per plate-height bin: frames, exact-read share, within-one-edit share, CER of the reads, sim-legible share."""
    out = []
    for lo, hi in itertools.pairwise(HEIGHT_BINS_PX):
        mine = [r for r in rows if lo <= r["plate_height_px"] < hi]
        if not mine:
            continue
        read = [r for r in mine if r["edits"] is not None]
        chars = sum(len(r["text"]) for r in read)
        out.append(
            {
                "bin": f"{lo}–{hi - 1}" if hi < 1000 else f"≥ {lo}",
                "lo_px": lo,
                "frames": len(mine),
                "exact": float(np.mean([r["edits"] == 0 for r in mine])),
                "near": float(np.mean([r["edits"] is not None and r["edits"] <= 1 for r in mine])),
                "cer": min(sum(r["edits"] for r in read) / chars, 1.0) if chars else None,
                "sim_legible": float(np.mean([r["sim_legible"] for r in mine])),
            }
        )
    return out


def _reader_model(rows: list[dict]) -> dict:
    """The sim reader's parameters that RapidOCR's reads of the sim-legible views imply: its read chance by the
    plate's width per character (`perception.text.read_probability`, fitted by maximum likelihood on a grid), and per
    character of each view's best reading (its cheapest edit, look-alikes at half an edit) the shares read as a
    look-alike, as another character, not at all, and inserted."""
    from bimfactor.localization.measurements.text import edit_distance, edit_operations

    legible = [r for r in rows if r["sim_legible"]]
    counts = dict.fromkeys(("same", "look_alike", "other", "dropped", "inserted"), 0)
    was_read = []
    for row in legible:
        texts = [t for t in row["read"] if t]
        was_read.append(bool(texts))
        if not texts:
            continue
        best = min(texts, key=lambda t: edit_distance(row["text"], t, 0.5))
        for key, n in edit_operations(row["text"], best, 0.5).items():
            counts[key] += n
    chars = max(counts["same"] + counts["look_alike"] + counts["other"] + counts["dropped"], 1)
    char_px = np.array([r["plate_width_px"] / max(len(r["text"]), 1) for r in legible], float)
    p_max, half_px, scale_px = _fit_read_chance(char_px, np.array(was_read, bool))
    return {
        "legible_views": len(legible),
        "read_share": float(np.mean(was_read)) if was_read else 0.0,
        "read_probability": p_max,
        "read_char_px": half_px,
        "read_char_scale_px": scale_px,
        "look_alike_rate": counts["look_alike"] / chars,
        "char_error_rate": counts["other"] / chars,
        "drop_rate": counts["dropped"] / chars,
        "insert_rate": counts["inserted"] / chars,
        "characters": counts,
    }


def _fit_read_chance(char_px: np.ndarray, read: np.ndarray) -> tuple[float, float, float]:
    """(most, half-way px, scale px) of `perception.text.read_probability` that make `read` likeliest; a grid search
    (most 0.30–1.00 by 0.01, half 0–20 px by 0.25, scale 0.25–5 px by 0.25)."""
    from bimfactor.perception.text import read_probability

    if not len(read):
        return 0.0, 0.0, 1.0
    most = np.arange(0.30, 1.0001, 0.01)[:, None, None, None]
    half = np.arange(0.0, 20.0001, 0.25)[None, :, None, None]
    scale = np.arange(0.25, 5.0001, 0.25)[None, None, :, None]
    p = np.clip(read_probability(char_px, most, half, scale), 1e-9, 1.0 - 1e-9)
    log_likelihood = np.where(read, np.log(p), np.log1p(-p)).sum(axis=-1)
    i, j, k = np.unravel_index(int(np.argmax(log_likelihood)), log_likelihood.shape)
    return float(most.ravel()[i]), float(half.ravel()[j]), float(scale.ravel()[k])


def _plot(table: list[dict], meta: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = np.arange(len(table))
    fig, ax = plt.subplots(figsize=(7, 3.6))
    ax.bar(x - 0.27, [100 * r["exact"] for r in table], 0.27, label="RapidOCR exact")
    ax.bar(x, [100 * r["near"] for r in table], 0.27, label="RapidOCR within 1 edit")
    ax.bar(x + 0.27, [100 * r["sim_legible"] for r in table], 0.27, label="sim reader: legible")
    ax.set_xticks(x, [f"{r['bin']}\n({r['frames']})" for r in table])
    ax.set_xlabel("plate height in the image, px (frames)")
    ax.set_ylabel("% of frames")
    ax.set_title(f"door plates read: {meta['camera']}", fontsize=10)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
