"""Screen-space error metrics (the LOD selection itself: :mod:`streamer.levels`).

Metrics share one vectorised signature, ``metric(delta, centre_xyz, radius, camera) -> rho_px``:
``delta`` ``(m,)`` object-space errors (metres), ``centre_xyz`` ``(m, 3)`` world centres of the
nodes' bounding spheres, ``radius`` ``(m,)`` their radii, and the result in pixels. A node with
``delta == 0`` always gets 0. :data:`METRICS` maps names to them; :data:`FIELD_FOR_METRIC` names
the static-error field (:mod:`tiler.static_error`) each is meant to be fed.

Qiu's selection splits a quadtree node while ``metric(delta) > tau``; a node at depth ``d`` is
drawn as a patch of ``2**patch_log2`` cells (level ``min(k, d + patch_log2)``), so its
``delta`` is the largest stored error of its descendants at depth ``d + patch_log2``.
:class:`streamer.levels.PatchErrorTable` does that for many blocks per frame; the per-node
reference selection it is tested against lives in ``tests/streamer/lod_reference.py``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from streamer.camera import Camera
from streamer.errors import LodError

Metric = Callable[[np.ndarray, np.ndarray, np.ndarray, Camera], np.ndarray]


def _inputs(
    delta: np.ndarray, centre_xyz: np.ndarray, camera: Camera
) -> tuple[np.ndarray, np.ndarray]:
    """``delta`` as float64 ``(m,)`` and the centres relative to the eye ``(m, 3)``."""
    c = np.asarray(centre_xyz, dtype=np.float64)
    if c.shape[-1:] != (3,):
        raise LodError(f"centre_xyz must be (m, 3) world points, got shape {c.shape}")
    rel = c - camera.eye
    d = np.asarray(delta, dtype=np.float64)
    if d.shape != rel.shape[:-1]:
        d = np.broadcast_to(d, rel.shape[:-1])
    return d, rel


def qiu_eq7(
    delta: np.ndarray, centre_xyz: np.ndarray, radius: np.ndarray, camera: Camera
) -> np.ndarray:
    """Qiu's Eq. 7: ``rho = H delta cos(theta) / (2 D tan(alpha/2) (1 + sin(beta)))``.

    ``H / (2 tan(alpha/2))`` is :attr:`Camera.focal_px` (``H`` = viewport height, ``alpha`` =
    vertical FOV). ``D`` = distance eye -> node centre. ``theta`` = angle between the sight line
    eye -> node and the horizontal terrain plane, so ``cos(theta) = horizontal distance / D``: a
    vertical error seen from straight above is foreshortened to nothing (per node rather than
    the camera pitch, which would zero every node of a camera looking straight down).
    ``beta`` = angle between the view direction and eye -> node, clamped to ``[0, pi/2]`` (nodes
    behind get the smallest weight, 1/2, instead of growing again as ``sin`` falls).
    Guard for D -> 0: an eye inside the node's bounding sphere (``D <= radius``) gives ``inf``
    (split, as Lee & Shin do), since the centre's direction then says nothing about the node
    (a camera over a block's centre would otherwise never split its root); ``D`` is also
    clamped below at ``near``. Not an upper bound on the screen error (measure it).
    """
    d, rel = _inputs(delta, centre_xyz, camera)
    x, y, z = rel[..., 0], rel[..., 1], rel[..., 2]
    h2 = x * x + y * y
    dist = np.sqrt(h2 + z * z)
    fwd = camera.forward
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = 1.0 / dist
        cos_t = np.sqrt(h2) * inv
        cos_b = (x * fwd[0] + y * fwd[1] + z * fwd[2]) * inv
    zero = dist == 0.0
    if zero.any():
        cos_t[zero] = 1.0
        cos_b[zero] = 1.0
    sin_b = np.sqrt(np.clip(1.0 - cos_b * cos_b, 0.0, 1.0))
    sin_b[cos_b < 0.0] = 1.0
    # delta inf (a mixed node) straight below the eye: inf * cos_t 0 is NaN, as the compiled
    # twin's (_plan_nb._qiu), and NaN is not <= tau: the node splits, without a warning
    with np.errstate(invalid="ignore"):
        rho = camera.focal_px * d * cos_t / (np.maximum(dist, camera.near) * (1.0 + sin_b))
    rho[dist <= radius] = np.inf
    rho[d == 0.0] = 0.0
    return rho


def conservative(
    delta: np.ndarray, centre_xyz: np.ndarray, radius: np.ndarray, camera: Camera
) -> np.ndarray:
    """Upper bound on the pixel shift of any in-view point of the sphere moved vertically by delta.

    ``rho = f delta sqrt(1 + tan^2(half diagonal FOV)) / z_min``, ``z_min`` = depth along the view
    axis of the sphere's nearest point. Derivation: a point at camera coordinates ``(x, y, z)``
    projects to ``f (x/z, y/z)``; moving it along the world up ``u`` (unit, camera coordinates)
    changes that at the rate ``(f/z) (u_xy - q u_z)`` per metre, ``q = (x/z, y/z)``. The matrix
    ``[I | -q]`` has singular values 1 and ``sqrt(1 + |q|^2)``, and inside the view
    ``|q|^2 <= tan^2(fov_x/2) + tan^2(fov_y/2)``; a segment between two in-view points stays in
    view (the frustum is convex) and inside the sphere has ``z >= z_min``; integrating over the
    ``delta`` metres gives the bound. ``inf`` when ``z_min <= near`` (eye inside the sphere, or
    it straddles the near plane); 0 when the sphere is wholly before ``near`` or beyond ``far``.
    """
    d, rel = _inputs(delta, centre_xyz, camera)
    r = np.broadcast_to(np.asarray(radius, dtype=np.float64), d.shape)
    depth = rel @ camera.forward
    z_min, z_max = depth - r, depth + r
    gain = camera.focal_px * math.sqrt(1.0 + camera.tan_half_diagonal**2)
    with np.errstate(divide="ignore", invalid="ignore"):
        rho = np.where(z_min > camera.near, gain * d / z_min, np.inf)
    unseen = (z_max < camera.near) | (z_min > camera.far) | (d == 0.0)
    return np.where(unseen, 0.0, rho)


def conservative_view(
    delta: np.ndarray,
    centre_xyz: np.ndarray,
    radius: np.ndarray,
    camera: Camera,
    half_extent: np.ndarray | None = None,
) -> np.ndarray:
    """:func:`conservative` with the slope bounded per node and per camera, not per view.

    Same claim (an upper bound on the pixel shift of any in-view point of the node's region
    moved vertically by delta, the moved point in the region and in view) and the same rate
    ``(f/z) (u_xy - q u_z)``, ``u`` = world up in camera coordinates. The region is the sphere
    ``(centre, radius)``, or with ``half_extent`` ``(m, 3)`` the axis-aligned world box
    ``centre ± half_extent`` (``radius`` is then not used: the box's half diagonal stands in for
    it). Let ``c`` be the centre in camera coordinates (``c_z`` depth, ``c_lat = (c_x, c_y)``),
    ``r`` the radius (box: half diagonal), ``w`` the region's half extent along each camera axis
    (sphere: ``r``; box: ``w_i = sum_j |R_ij| h_j``, ``R`` the world-to-camera rotation) and
    ``z_min = c_z - w_z > near`` (the depth of the region's nearest point). The segment from
    the point to the moved point lies in the region (convex) and in view (convex), so every
    point ``p = c + e`` of it has ``|e| <= r``, ``|e_i| <= w_i``, ``p_z >= z_min`` and, besides
    the view's own limit ``|q| <= T = tan(half diagonal FOV)``:

    * ``|q| = |c_lat + e_lat| / p_z <= Q = L / z_min``, ``L = |c_lat| + r`` (sphere) or
      ``min(|c_lat| + r, hypot(|c_x| + w_x, |c_y| + w_y))`` (box); hence
      ``|u_xy - q u_z| <= g1 = |u_xy| + |u_z| min(Q, T)``;
    * ``q - c_lat/c_z = (c_z e_lat - c_lat e_z) / (c_z p_z)`` whose numerator is two components
      of ``c x e``, so it is at most ``N = |c| r`` (box: also at most
      ``hypot(c_z w_x + |c_x| w_z, c_z w_y + |c_y| w_z)``, the smaller is used) and
      ``|u_xy - q u_z| <= g2 = |u_xy - (c_lat/c_z) u_z| + |u_z| N / (c_z z_min)``.

    Both bounds hold at every point of the segment and ``1/p_z <= 1/z_min``; integrating over
    the ``delta`` metres gives ``rho = f delta min(g1, g2) / z_min``. By Cauchy-Schwarz
    ``g1 <= sqrt(|u_xy|^2 + u_z^2) sqrt(1 + T^2) = sqrt(1 + T^2)``: never above
    :func:`conservative` for the same sphere (a camera looking level has ``u_z = 0`` and gain
    ``f``, the FOV drops out). Same ``inf`` and 0 cases as :func:`conservative` (for the box:
    its depth range ``c_z ± w_z``). The selection feeds boxes to the metrics in
    :data:`BOX_METRICS` (:func:`takes_box`).
    """
    d, rel = _inputs(delta, centre_xyz, camera)
    basis = np.stack([camera.right, camera.up, camera.forward])
    c = rel @ basis.T
    cz, c_lat = c[..., 2], np.hypot(c[..., 0], c[..., 1])
    ux, uy, uz = basis[:, 2]  # world up (0, 0, 1) in camera coordinates
    u_lat = math.hypot(ux, uy)
    if half_extent is None:
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), d.shape)
        wz = r
    else:
        h = np.abs(np.broadcast_to(np.asarray(half_extent, dtype=np.float64), c.shape))
        w = h @ np.abs(basis).T
        wz = w[..., 2]
        r = np.linalg.norm(h, axis=-1)
    z_min, z_max = cz - wz, cz + wz
    c_norm = np.linalg.norm(c, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        lat = c_lat + r
        num = c_norm * r
        if half_extent is not None:
            ax, ay = np.abs(c[..., 0]), np.abs(c[..., 1])
            lat = np.minimum(lat, np.hypot(ax + w[..., 0], ay + w[..., 1]))
            num = np.minimum(num, np.hypot(cz * w[..., 0] + ax * wz, cz * w[..., 1] + ay * wz))
        q_node = np.minimum(lat / z_min, camera.tan_half_diagonal)
        g1 = u_lat + abs(uz) * q_node
        centre_rate = np.hypot(ux - c[..., 0] / cz * uz, uy - c[..., 1] / cz * uz)
        g2 = centre_rate + abs(uz) * num / (cz * z_min)
        gain = camera.focal_px * np.minimum(g1, g2)
        rho = np.where(z_min > camera.near, gain * d / z_min, np.inf)
    unseen = (z_max < camera.near) | (z_min > camera.far) | (d == 0.0)
    return np.where(unseen, 0.0, rho)


def horizontal_px(
    width: np.ndarray,
    centre_xyz: np.ndarray,
    radius: np.ndarray,
    camera: Camera,
    half_extent: np.ndarray | None = None,
) -> np.ndarray:
    """Upper bound in pixels on the projected length of any in-view segment of length ``width``
    (metres, any direction) inside the node's sphere ``(centre, radius)`` or, with
    ``half_extent``, its box (the nodata rule ``"gap"``: the extent of a mixed cell).

    ``rho = f width sqrt(1 + Q^2) / z_min``: the rate of a unit direction ``u`` is
    ``(f/z)(u_xy - q u_z)``, and ``[I | -q]`` has largest singular value ``sqrt(1 + |q|^2)``
    (:func:`conservative`), with ``|q| <= Q = min(L / z_min, T)`` along the segment
    (:func:`conservative_view`'s ``L``, ``T`` = tan of the half diagonal FOV). Unlike the
    vertical metrics it is not foreshortened looking straight down (a horizontal gap is seen
    whole from above). Same ``inf`` and 0 cases as :func:`conservative_view`.
    """
    d, rel = _inputs(width, centre_xyz, camera)
    basis = np.stack([camera.right, camera.up, camera.forward])
    c = rel @ basis.T
    cz, c_lat = c[..., 2], np.hypot(c[..., 0], c[..., 1])
    if half_extent is None:
        r = np.broadcast_to(np.asarray(radius, dtype=np.float64), d.shape)
        wz, lat = r, c_lat + r
    else:
        h = np.abs(np.broadcast_to(np.asarray(half_extent, dtype=np.float64), c.shape))
        w = h @ np.abs(basis).T
        wz = w[..., 2]
        r = np.linalg.norm(h, axis=-1)
        ax, ay = np.abs(c[..., 0]), np.abs(c[..., 1])
        lat = np.minimum(c_lat + r, np.hypot(ax + w[..., 0], ay + w[..., 1]))
    z_min, z_max = cz - wz, cz + wz
    with np.errstate(divide="ignore", invalid="ignore"):
        q = np.minimum(lat / z_min, camera.tan_half_diagonal)
        rho = camera.focal_px * d * np.sqrt(1 + q * q) / z_min
        rho = np.where(z_min > camera.near, rho, np.inf)
    unseen = (z_max < camera.near) | (z_min > camera.far) | (d == 0.0)
    return np.where(unseen, 0.0, rho)


def check_finite_tau(tau: float) -> float:
    """``tau`` as a float, or :class:`LodError` unless it is a finite number >= 0: a mixed
    terrain/nodata node splits because its error, ``inf``, exceeds tau (``inf > inf`` does
    not), and :func:`gap_scale` would make ``0 * inf = nan``."""
    try:
        t = float(tau)
        ok = t >= 0.0 and math.isfinite(t)
    except (TypeError, ValueError, OverflowError):
        ok = False
    if not ok:
        raise LodError(f"tau must be a finite pixel threshold >= 0, got {tau!r}")
    return t


def gap_scale(tau: float) -> float:
    """The nodata rule ``"gap"``'s factor on a mixed cell's :func:`horizontal_px`: a node then
    has ``rho > tau`` while the cell spans more than ``min(tau, 1)`` px, ``tau / min(tau, 1)``
    (0 at tau 0, where every node splits anyway); :class:`LodError` for a tau that is not
    finite (:func:`check_finite_tau`)."""
    t = check_finite_tau(tau)
    return t / min(t, 1.0) if t > 0 else 0.0


def exact_projected(delta: np.ndarray, points: np.ndarray, camera: Camera) -> np.ndarray:
    """Jung & Han's exact screen error: pixel distance between B and B + delta*up (NaN behind)."""
    p = np.asarray(points, dtype=np.float64)
    d = np.broadcast_to(np.asarray(delta, dtype=np.float64), p.shape[:-1])
    moved = p.copy()
    moved[..., 2] += d
    x0, y0, _ = camera.project(p)
    x1, y1, _ = camera.project(moved)
    return np.hypot(x1 - x0, y1 - y0)


METRICS: dict[str, Metric] = {
    "qiu": qiu_eq7,
    "conservative": conservative,
    "conservative-view": conservative_view,
}
FIELD_FOR_METRIC: dict[str, str] = {
    "qiu": "qiu",
    "conservative": "bound",
    "conservative-view": "bound",
}


#: metrics that take a node's box (``half_extent=`` keyword) instead of its sphere: the
#: selection then gives each node its own height range (:mod:`render.node_boxes`)
BOX_METRICS: frozenset[Metric] = frozenset({conservative_view})


def takes_box(metric: str | Metric) -> bool:
    """Whether the selection should give ``metric`` node boxes: one of :data:`BOX_METRICS`,
    or a callable with a true ``takes_box`` attribute."""
    fn = get_metric(metric)
    return fn in BOX_METRICS or bool(getattr(fn, "takes_box", False))


def get_metric(metric: str | Metric) -> Metric:
    """A metric from :data:`METRICS` by name, or the callable itself."""
    if callable(metric):
        return metric
    try:
        return METRICS[metric]
    except (KeyError, TypeError):
        raise LodError(f"unknown metric {metric!r}; choose one of {sorted(METRICS)}") from None
