"""The default registrar on simulated paper-floor keyframes (noisy depth), and the comparison's plumbing."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bimfactor.evaluation.registrars import (
    compare_registrars,
    initial_error_sweep,
    make_registrars,
    perturb,
    plot_basins,
    summarize,
)
from bimfactor.registration.gate import gate_registration
from bimfactor.registration.icp import make_registrar
from bimfactor.types import wrap_angle

from ..sim.conftest import Building

START_TRANS_M, START_ROT_DEG = 0.3, 5.0


def test_default_registrar_from_a_perturbed_start(paper_floor: Building, keyframes_and_surfaces) -> None:
    keyframes, surfaces = keyframes_and_surfaces
    assert len(keyframes) == 3
    rc = paper_floor.cfg.registration
    registrar = make_registrar(rc)
    rng = np.random.default_rng(7)
    for key in keyframes:
        gt = key.frame.gt_pose
        for _ in range(3):
            init = perturb(gt, START_TRANS_M, np.deg2rad(START_ROT_DEG), rng)
            result = registrar.register(key.scan_base, surfaces[key.frame.gt_storey], init)
            trans_err = np.hypot(*(result.pose[:2] - gt[:2]))
            rot_err = abs(np.rad2deg(wrap_angle(result.pose[2] - gt[2])))
            assert trans_err < 0.05 and rot_err < 1.0, (key.frame.index, trans_err, rot_err)
            assert gate_registration(result, init, rc).accepted


def test_comparison_records_summary_and_plot(paper_floor: Building, keyframes_and_surfaces, tmp_path: Path) -> None:
    keyframes, surfaces = keyframes_and_surfaces
    rc = paper_floor.cfg.registration.model_copy(update={"compare_perturbations": 3})
    sweep = initial_error_sweep(rc)
    assert sweep.shape == (3, 2) and sweep[0, 0] == 0.0 and sweep[-1, 0] == rc.compare_max_trans_m
    assert sorted(np.rad2deg(sweep[:, 1]).round(6)) == [0.0, rc.compare_max_rot_deg / 2, rc.compare_max_rot_deg]
    registrars = make_registrars(rc, ["planar", "point_to_plane"])
    records = compare_registrars(
        paper_floor.prior, paper_floor.model, paper_floor.cfg, keyframes[:1], registrars, sweep, 0, surfaces
    )
    assert len(records) == 1 * 3 * 2
    summary = summarize(records)
    assert [s["registrar"] for s in summary] == ["planar", "point_to_plane"]
    assert all(0.0 <= s["success_rate"] <= 1.0 and s["median_time_ms"] > 0 for s in summary)
    assert sorted({r["init_trans_m"] for r in records}) == sorted(sweep[:, 0].tolist())
    for r in records:
        assert r["success"] == (r["final_trans_m"] < rc.success_trans_m and r["final_rot_deg"] < rc.success_rot_deg)
        # The probes only ever take acceptances away; rejected runs carry their reasons.
        assert r["accepted_without_probes"] or not r["accepted"]
        assert r["accepted_without_probes"] or not r["accepted_coarse"]
        assert bool(r["reasons"]) != r["accepted"]
    for s in summary:
        assert s["accepted_wrong"] <= s["accepted_without_probes_wrong"]
    png = plot_basins(records, tmp_path / "basins.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
