"""``geometry-splitting``, the CPU reference (float64, no GL) of the GPU expansion passes: the
same culling, caps and split flag over the same quadtree texture, so the tests can compare the
GPU's leaves and splits with it node for node."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from render.strategies.geometry_splitting.pure import projected_error
from streamer.camera import Camera

Block = tuple[int, int]

if TYPE_CHECKING:
    from render.strategies.geometry_splitting.gl import GeometrySplitting

#: relative sphere margin of the frustum test (float32 safety); the GPU's ``CULL_MARGIN``
CULL_MARGIN = 1e-4


def expand_reference(
    st: GeometrySplitting, camera: Camera, tau: float, resident: dict[Block, int] | None = None
) -> tuple[list[int], np.ndarray, np.ndarray]:
    """CPU twin (float64) of the expansion: node counts after each pass, the leaves and the
    nodes that split, both ``(block index, depth, row, col)`` sorted."""
    blocks, t = st.block_table(resident)
    k, g = st.k, st.r.grid
    trees = [st.gpu_tree(b, int(t[i, 3])) for i, b in enumerate(blocks)]
    mvp = camera.projection_matrix() @ camera.view_matrix()
    planes = []
    for i in range(3):
        for sg in (-1.0, 1.0):
            p = mvp[3] + sg * mvp[i]
            planes.append(p / np.linalg.norm(p[:3]))
    planes = np.array(planes)

    zlo_t, zhi_t = st.r.terrain_zrange
    # spheres by hand, not tiler.quadtree: the GPU's rule (radius = half diagonal + half height
    # range, centres from sample_xy), which this twin must match operation for operation

    def cull(b, d, row, col):
        s = np.left_shift(1, k - d).astype(np.float64)
        x, y = g.sample_xy(t[b, 1] + row * s + 0.5 * s, t[b, 0] + col * s + 0.5 * s)
        c = np.stack([x, y, np.full(len(b), 0.5 * (zlo_t + zhi_t))], 1) - camera.eye
        return c, 0.5 * s * math.hypot(g.dx, g.dy) + 0.5 * (zhi_t - zlo_t)

    def sphere(b, d, row, col):
        dd = np.minimum(d, k - 1)
        sh = d - dd
        sig = np.zeros(len(b))
        zlo, zhi = np.zeros(len(b)), np.zeros(len(b))
        for i in range(len(b)):
            tr = trees[b[i]]
            rr, cc = row[i] >> sh[i], col[i] >> sh[i]
            sig[i] = tr.sigma[dd[i]][rr, cc] if d[i] < k else 0.0
            zlo[i], zhi[i] = tr.zmin[dd[i]][rr, cc], tr.zmax[dd[i]][rr, cc]
        s = np.left_shift(1, k - d).astype(np.float64)
        gx = t[b, 0] + col * s + 0.5 * s
        gy = t[b, 1] + row * s + 0.5 * s
        x, y = g.sample_xy(gy, gx)
        c = np.stack([x, y, 0.5 * (zlo + zhi)], 1) - camera.eye
        rad = 0.5 * s * math.hypot(g.dx, g.dy) + 0.5 * (zhi - zlo)
        return c, rad, sig, s

    def visible(c, rad):
        dist = c @ planes[:, :3].T + planes[:, 3]
        return (dist >= -rad[:, None] * (1.0 + CULL_MARGIN)).all(axis=1)

    def splits(b, d, row, col):
        c, rad, sig, s = sphere(b, d, row, col)
        cap = t[b, 3]
        ok = d < cap
        for dr, (v, ones) in enumerate(((row, False), (col, True), (row, True), (col, False))):
            m = np.left_shift(1, d) - 1
            x = (~v if ones else v) & m
            lead = np.where(x == 0, d, d - 1 - np.floor(np.log2(np.maximum(x, 1))))
            ok &= lead < t[b, 12 + dr]
        rho = projected_error(c, sig, s, camera, g.dx, g.dy)
        inside = np.linalg.norm(c, axis=1) - rad < 0.0
        fl = np.where(inside, sig != 0.0, tau <= rho) | np.isinf(sig)  # inf: a mask boundary
        return ok & fl

    n = len(blocks)
    b = np.arange(n)
    d = np.zeros(n, np.int64)
    row = np.zeros(n, np.int64)
    col = np.zeros(n, np.int64)
    done = np.zeros(n, bool)
    keep = visible(*cull(b, d, row, col))
    b, d, row, col, done = b[keep], d[keep], row[keep], col[keep], done[keep]
    counts, split = [], []
    for _ in range(k):
        sp = ~done & splits(b, d, row, col)
        split.append(np.stack([b[sp], d[sp], row[sp], col[sp]], 1))
        cb = np.repeat(b[sp], 4)
        cd = np.repeat(d[sp] + 1, 4)
        cr = (2 * row[sp][:, None] + np.array([0, 0, 1, 1])).ravel()
        cc = (2 * col[sp][:, None] + np.array([0, 1, 0, 1])).ravel()
        v = visible(*cull(cb, cd, cr, cc))
        b = np.concatenate([b[~sp], cb[v]])
        d = np.concatenate([d[~sp], cd[v]])
        row = np.concatenate([row[~sp], cr[v]])
        col = np.concatenate([col[~sp], cc[v]])
        done = np.concatenate([np.ones(int((~sp).sum()), bool), np.zeros(int(v.sum()), bool)])
        counts.append(len(b))
        if not len(b):
            break
    leaves = np.stack([b, d, row, col], 1)
    split = np.concatenate(split) if split else np.zeros((0, 4), np.int64)
    return counts, leaves[np.lexsort(leaves.T[::-1])], split[np.lexsort(split.T[::-1])]
