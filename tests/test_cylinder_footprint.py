"""Blocks straddling the sample's outline are not samples (core/extraction/cylinder.py,
``surface_samples(..., footprint_half_px=1)``, used by extract.rotation_geometry)."""
from __future__ import annotations

import numpy as np

from glossrig.core.extraction.cylinder import surface_samples

SCALE = 0.06


def _cast(rig, u, v, **kw):
    cam = rig.camera
    R, t = cam.pose()
    return surface_samples(cam.matrix(SCALE), cam.distortion, cam.size(SCALE), R, t, np.eye(3), np.zeros(3),
                           rig.cylinder_radius, rig.sample_height, pixels=(u, v), **kw)


def test_kept_blocks_lie_wholly_on_the_sample_and_only_outline_blocks_go(rig):
    w, h = rig.camera.size(SCALE)
    bj, bi = np.meshgrid(np.arange(w // 2), np.arange(h // 2))
    u, v = 2 * bj.ravel() + 0.5, 2 * bi.ravel() + 0.5
    centre = _cast(rig, u, v)
    whole = _cast(rig, u, v, footprint_half_px=1.0)
    assert len(whole.u) > 500
    # every kept block's four footprint corners meet the sample
    for du in (-1.0, 1.0):
        for dv in (-1.0, 1.0):
            assert len(_cast(rig, whole.u + du, whole.v + dv).u) == len(whole.u)
    # the kept blocks are centre hits, with the same surface points
    kept = set(zip(whole.u.tolist(), whole.v.tolist()))
    hits = {k: i for i, k in enumerate(zip(centre.u.tolist(), centre.v.tolist()))}
    assert kept <= set(hits)
    idx = [hits[k] for k in zip(whole.u.tolist(), whole.v.tolist())]
    np.testing.assert_array_equal(centre.points[idx], whole.points)
    # a dropped block is on the outline: one of its 8 neighbours' centres misses the sample
    dropped = set(hits) - kept
    assert dropped, "the outline has blocks whose footprint leaves the sample"
    for (du_, dv_) in dropped:
        neighbours = {(du_ + a, dv_ + b) for a in (-2, 0, 2) for b in (-2, 0, 2)} - {(du_, dv_)}
        assert not neighbours <= set(hits), (du_, dv_)
    # and a dropped block has a footprint corner off the sample (cast on its own)
    du_, dv_ = (np.array(c, float) for c in zip(*sorted(dropped)))
    corner_hits = [len(_cast(rig, du_[k:k + 1] + a, dv_[k:k + 1] + b).u)
                   for k in range(len(du_)) for a in (-1.0, 1.0) for b in (-1.0, 1.0)]
    assert (np.array(corner_hits).reshape(-1, 4).min(axis=1) == 0).all()
