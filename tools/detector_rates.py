"""How often the shipped detector (YOLOX-Nano) finds, misses, confuses and invents objects on real frames: the rates of
the `yolox` sim perception preset (bimfactor/configs/perception_sim.yaml).

The ground truth is counted by eye, per frame, in the five frames of ../shared/data/real/slambook-dining and every
third frame of ../shared/data/real/tum-fr1-rpy (20 frames): the objects of the classes the detector can report under
the prior's vocabulary (chairs and armchairs, dining tables, sofas, screens), each counted when about half of it or
more is in view and not blurred beyond recognition (`GROUND_TRUTH`). The detector runs as localization runs it
(`perception.yolox`, the COCO → vocabulary table, perception.box_threshold); per frame and class a detection is a true
one up to the number counted, the rest are false, the rest of the count missed. Screens: a BIM model calls a monitor
"computer"; YOLOX calls it "tv" (→ television) about as often as "laptop" (→ computer), and a television read off a
screen counts as found but confused. Writes the rates as JSON to stdout and, with --figure, the detector's boxes on
slambook frame 1 and three tum-fr1-rpy frames (docs/figures/yolox-real-frames.png). Run from the repository root:

    .venv/bin/python tools/detector_rates.py --figure docs/figures/yolox-real-frames.png
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

# What is in view, counted by eye: {frame file: {class: count}}; "screen" is a monitor or a laptop's screen.
GROUND_TRUTH: dict[str, dict[str, dict[str, int]]] = {
    "slambook-dining": {
        "1.png": {"chair": 7, "dining table": 1},
        "2.png": {"chair": 4, "dining table": 1},
        "3.png": {"chair": 4, "dining table": 1},
        "4.png": {"chair": 2, "sofa": 1},
        "5.png": {"chair": 2, "sofa": 1},
    },
    # every third frame of rgb.txt, from the first; the screens of both desks and the office chairs
    "tum-fr1-rpy": {
        "0": {"screen": 2},
        "3": {"screen": 2, "chair": 1},
        "6": {"screen": 1},
        "9": {"screen": 2},
        "12": {"screen": 1, "chair": 1},
        "15": {"screen": 1, "chair": 1},
        "18": {"screen": 1},
        "21": {"screen": 2, "chair": 1},
        "24": {},
        "27": {"screen": 2, "chair": 1},
        "30": {"screen": 1},
        "33": {"screen": 1},
        "36": {"screen": 2, "chair": 1},
        "39": {"screen": 1, "chair": 1},
        "42": {"screen": 1},
        "45": {"screen": 1, "chair": 1},
        "48": {"screen": 4, "chair": 1},
        "51": {"screen": 1},
        "54": {"screen": 1, "chair": 1},
        "57": {"screen": 2, "chair": 1},
    },
}
AS_COUNTED = {"chair": "chair", "dining table": "dining table", "sofa": "sofa", "computer": "screen",
              "television": "screen"}  # fmt: skip
"""The vocabulary label a detection carries → the class it is counted against (others: false)."""
CONFUSED = {"television"}
"""Labels that find a counted object under another label than the BIM's (a monitor is a "computer" in IFC)."""
FIGURE_FRAMES = (("slambook-dining", "1.png"), ("tum-fr1-rpy", "15"), ("tum-fr1-rpy", "36"), ("tum-fr1-rpy", "57"))


def frames(root: Path) -> list[tuple[str, str, Path]]:
    """(recording, key, colour image path) of every counted frame."""
    out = []
    for recording, table in GROUND_TRUTH.items():
        folder = root / recording
        listed = [line.split()[1] for line in (folder / "rgb.txt").read_text().splitlines() if line and line[0] != "#"]
        for key in table:
            name = key if key.endswith(".png") else listed[int(key)]
            out.append((recording, key, folder / (name if "/" in name else f"rgb/{name}")))
    return out


def measure(root: Path) -> dict:
    import cv2

    from bimfactor.config import load_config
    from bimfactor.embed.text import make_text_embedder
    from bimfactor.perception.pipeline import vocabulary_of
    from bimfactor.perception.yolox import YoloxDetector, coco_label_table
    from bimfactor.types import Frame

    cfg = load_config(None)
    p = cfg.perception
    table = coco_label_table(vocabulary_of(cfg), make_text_embedder(cfg.embed), p.sim_threshold)
    detector = YoloxDetector(table, max(p.box_threshold, p.text_threshold))
    totals: Counter[str] = Counter()
    per_frame = []
    for recording, key, path in frames(root):
        rgb = cv2.imread(str(path))[..., ::-1]
        found = detector.detect(
            Frame(0, 0.0, np.ascontiguousarray(rgb), np.zeros(rgb.shape[:2], np.float32), np.zeros(3))
        )
        truth = GROUND_TRUTH[recording][key]
        by_class: dict[str, list[str]] = {}
        false = 0
        for d in found:
            counted = AS_COUNTED.get(d.label)
            if counted is None:
                false += 1
            else:
                by_class.setdefault(counted, []).append(d.label)
        true = confused = missed = 0
        for cls in set(truth) | set(by_class):
            labels = sorted(by_class.get(cls, []), key=lambda label: label in CONFUSED)  # right labels first
            n = truth.get(cls, 0)
            true += min(n, len(labels))
            confused += sum(label in CONFUSED for label in labels[:n])
            false += max(len(labels) - n, 0)
            missed += max(n - len(labels), 0)
        totals.update(objects=sum(truth.values()), true=true, confused=confused, false=false, missed=missed, frames=1)
        per_frame.append({"recording": recording, "frame": key, "truth": truth,
                          "detections": [[d.label, round(d.box_score, 2)] for d in found]})  # fmt: skip
    return {
        "frames": totals["frames"],
        "objects": totals["objects"],
        "recall": totals["true"] / totals["objects"],
        "confusion_rate": totals["confused"] / max(totals["true"], 1),
        "false_per_frame": totals["false"] / totals["frames"],
        "counts": dict(totals),
        "per_frame": per_frame,
    }


def figure(root: Path, path: Path) -> None:
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bimfactor.config import load_config
    from bimfactor.evaluation.plots import save_figure
    from bimfactor.perception.yolox import COCO_CLASSES, LabelTable, YoloxDetector

    cfg = load_config(None)
    detector = YoloxDetector(LabelTable.coco(), cfg.perception.box_threshold)
    paths = {(r, k): p for r, k, p in frames(root)}
    fig, axes = plt.subplots(2, 2, figsize=(12, 9.2))
    for ax, key in zip(axes.ravel(), FIGURE_FRAMES, strict=True):
        bgr = cv2.imread(str(paths[key]))
        boxes, scores, classes = detector.raw(bgr)
        ax.imshow(bgr[..., ::-1])
        for (x0, y0, x1, y1), s, c in zip(boxes, scores, classes, strict=True):
            name = COCO_CLASSES[int(c)]
            colour = "tab:green" if name in ("chair", "dining table", "couch", "tv", "laptop") else "tab:orange"
            ax.add_patch(plt.Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, lw=2, edgecolor=colour))
            ax.text(x0 + 2, y0 + 12, f"{name} {s:.2f}", color="white", fontsize=8,
                    bbox={"facecolor": colour, "alpha": 0.8, "pad": 1, "lw": 0})  # fmt: skip
        ax.set_title(f"{key[0]} {key[1]}", fontsize=10)
        ax.axis("off")
    fig.suptitle("YOLOX-Nano on real frames: green, classes the vocabulary maps; orange, classes it drops", fontsize=11)
    save_figure(fig, path, dpi=90)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--real", type=Path, default=Path("../shared/data/real"), help="the real recordings' folder")
    parser.add_argument("--figure", type=Path, help="write the detector's boxes on four real frames here")
    args = parser.parse_args(argv)
    if not all((args.real / name / "rgb.txt").is_file() for name in GROUND_TRUTH):
        print(f"error: the real recordings are not in {args.real}", file=sys.stderr)
        return 2
    result = measure(args.real)
    print(json.dumps({k: v for k, v in result.items() if k != "per_frame"}, indent=1))
    if args.figure is not None:
        figure(args.real, args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
