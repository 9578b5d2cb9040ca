"""Ground-plane culling shapes and intersection tests (numpy and Python floats, float64).

* :func:`view_triangle` — Qiu et al.'s projected view frustum: an isosceles triangle with its
  apex at the camera's ground position, its axis along the horizontal view direction (from yaw)
  and its legs at +-half the horizontal FOV, ``atan(aspect * tan(fov_y/2))``. Roll is ignored
  (Qiu's camera has none). Leg length ``R`` (:func:`qiu_reach`) is chosen so the far side lies
  at the *horizontal reach of the far plane* along the axis, the largest of the far corners'
  horizontal distances along it: ``far * (cos(pitch) + tan(fov_y/2) * |sin(pitch)|)``; so
  ``R = that / cos(half_fov_x)``. At pitch 0 the triangle is exactly the frustum's horizontal
  trace. It is an approximation otherwise: a pitched camera's side planes meet the ground along
  lines that start behind the camera and are narrower, so the triangle misses the view's lower
  corners close to the camera (and everything below and behind a steeply pitched one). Given
  the terrain's heights, a camera looking above the horizon (pitch > 0) reaches only as far as
  its frustum meets them (:func:`ground_reach`): pitched up with its whole frustum above the
  terrain, it sees no ground and its triangle is empty.
* :func:`frustum_hull` — Jung & Han's convex hull of the 8 frustum corners projected on the
  ground: the exact shadow of the whole frustum, optionally clipped to a slab of heights
  ``zrange`` first (tighter, still exact for terrain inside that range).
* :func:`extension_triangle` — Qiu's frustum extension (Sect. 4, Eq. 8): the similar triangle
  with its apex moved back by ``L`` and its far side pushed out by ``S``.
* :func:`polygon_meets_rects` / :func:`polygon_meets_circles` — exact, vectorised tests of a
  convex polygon against many axis-aligned rectangles (separating axes) or circles. Shapes are
  closed: touching counts as meeting.
* :func:`blocks_meeting` / :func:`visible_sets` — the block sets ``M`` (frustum) and ``N``
  (extension) of a :class:`tiler.grid.BlockGrid`.

All polygons are ``(n, 2)`` float64 world ``(x, y)`` arrays, counter-clockwise. Tests subtract a
local origin first so that coordinates near 1e7 m keep their precision.
"""

from __future__ import annotations

import math

import numpy as np

from streamer.camera import Camera
from streamer.errors import FrustumError
from tiler.grid import BlockGrid

# The 12 edges of the frustum as pairs of indices into Camera.frustum_corners_rel().
_EDGE_PAIRS = (
    (0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)
)  # fmt: skip


# --- polygons ---------------------------------------------------------------------------------


def convex_hull(points: np.ndarray) -> np.ndarray:
    """Counter-clockwise convex hull of ``(n, 2)`` points (monotone chain, no repeated ends)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros((0, 2))
    origin = pts.min(axis=0)
    # the distinct points sorted by x then y (np.unique(axis=0)'s order, on Python floats:
    # the same arithmetic as numpy scalars, without their cost)
    pl = sorted(set(map(tuple, (pts - origin).tolist())))
    if len(pl) <= 2:
        return np.array(pl, dtype=np.float64).reshape(-1, 2) + origin

    def turns_left(o: tuple, a: tuple, b: tuple) -> bool:
        """Strict left turn o -> a -> b; near-collinear (relative 1e-12) counts as not."""
        ax, ay, bx, by = a[0] - o[0], a[1] - o[1], b[0] - o[0], b[1] - o[1]
        return ax * by - ay * bx > 1e-12 * math.hypot(ax, ay) * math.hypot(bx, by)

    lower: list[tuple] = []
    for p in pl:
        while len(lower) >= 2 and not turns_left(lower[-2], lower[-1], p):
            lower.pop()
        lower.append(p)
    upper: list[tuple] = []
    for p in reversed(pl):
        while len(upper) >= 2 and not turns_left(upper[-2], upper[-1], p):
            upper.pop()
        upper.append(p)
    hull = np.array(lower[:-1] + upper[:-1], dtype=np.float64)
    return hull + origin


def as_polygon(polygon: np.ndarray) -> np.ndarray:
    """Validate a convex polygon as ``(n, 2)`` finite float64, counter-clockwise."""
    p = np.asarray(polygon, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise FrustumError(f"polygon must be an (n, 2) array of (x, y), got shape {p.shape}")
    if not np.isfinite(p).all():
        raise FrustumError(f"polygon must be finite, got {p.tolist()}")
    if _area2(p) < 0.0:
        p = p[::-1]
    return p


def _area2(p: np.ndarray) -> float:
    """Twice the signed area of a polygon (positive when counter-clockwise)."""
    if len(p) < 3:
        return 0.0
    q = p - p[0]
    return float(np.sum(q[:-1, 0] * q[1:, 1] - q[1:, 0] * q[:-1, 1]))


def polygon_meets_rects(
    polygon: np.ndarray,
    xmin: np.ndarray,
    ymin: np.ndarray,
    xmax: np.ndarray,
    ymax: np.ndarray,
) -> np.ndarray:
    """Boolean per rectangle: the closed convex polygon and the closed rectangle meet (SAT).

    Axes tested: x, y and every polygon edge normal (sufficient for convex shapes).
    """
    poly = as_polygon(polygon)
    xmin, ymin, xmax, ymax = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (xmin, ymin, xmax, ymax))
    )
    if len(poly) == 0:
        return np.zeros(xmin.shape, dtype=bool)
    o = poly[0]
    p = poly - o
    cx = ((xmin - o[0]) + (xmax - o[0])) * 0.5
    cy = ((ymin - o[1]) + (ymax - o[1])) * 0.5
    hx = (xmax - xmin) * 0.5
    hy = (ymax - ymin) * 0.5
    hit = (
        (xmin - o[0] <= p[:, 0].max())
        & (xmax - o[0] >= p[:, 0].min())
        & (ymin - o[1] <= p[:, 1].max())
        & (ymax - o[1] >= p[:, 1].min())
    )
    if len(p) >= 2:
        e = np.roll(p, -1, axis=0) - p
        normals = np.stack([-e[:, 1], e[:, 0]], axis=1)  # (n, 2)
        proj = p @ normals.T  # (n_vertices, n_axes)
        pmin, pmax = proj.min(axis=0), proj.max(axis=0)
        c = cx[..., None] * normals[:, 0] + cy[..., None] * normals[:, 1]
        r = hx[..., None] * np.abs(normals[:, 0]) + hy[..., None] * np.abs(normals[:, 1])
        hit &= ((c - r <= pmax) & (c + r >= pmin)).all(axis=-1)
    return hit


def polygon_meets_circles(
    polygon: np.ndarray, cx: np.ndarray, cy: np.ndarray, radius: np.ndarray
) -> np.ndarray:
    """Boolean per circle: the closed convex polygon and the closed disc meet.

    True when the centre is inside the polygon or within ``radius`` of one of its edges.
    """
    poly = as_polygon(polygon)
    cx, cy, radius = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (cx, cy, radius))
    )
    if len(poly) == 0:
        return np.zeros(cx.shape, dtype=bool)
    o = poly[0]
    p = poly - o
    q = np.stack([cx - o[0], cy - o[1]], axis=-1)[..., None, :]  # (..., 1, 2)
    a = p
    e = np.roll(p, -1, axis=0) - p  # (n, 2)
    ee = np.einsum("ij,ij->i", e, e)
    aq = q - a  # (..., n, 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(ee > 0.0, np.einsum("...ij,ij->...i", aq, e) / ee, 0.0)
    t = np.clip(t, 0.0, 1.0)
    d = aq - t[..., None] * e
    dist2 = np.einsum("...ij,...ij->...i", d, d).min(axis=-1)
    near = dist2 <= radius * radius
    if _area2(p) > 0.0:
        crossz = e[:, 0] * aq[..., 1] - e[:, 1] * aq[..., 0]
        near |= (crossz >= 0.0).all(axis=-1)
    return near


# --- Qiu's triangle and its extension ---------------------------------------------------------


def qiu_reach(camera: Camera, zrange: tuple[float, float] | None = None) -> float:
    """Leg length ``R`` of Qiu's triangle: far-plane horizontal reach / cos(half FOV x).

    With ``zrange`` (the terrain's heights) a camera looking above the horizon (pitch > 0)
    reaches only as far along its axis as its frustum meets that slab (0: it sees no ground).
    """
    p = math.radians(camera.pitch)
    reach = camera.far * (math.cos(p) + camera.tan_half_y * abs(math.sin(p)))
    if zrange is not None and camera.pitch > 0.0:
        reach = min(reach, ground_reach(camera, zrange))
    return reach / math.cos(math.atan(camera.tan_half_x))


def ground_reach(camera: Camera, zrange: tuple[float, float]) -> float:
    """How far ahead (along the horizontal view direction) the frustum's part within the slab
    of heights ``zrange`` reaches; 0 when that part is empty or lies behind the camera."""
    pts = _slab_points(camera, zrange)
    hx, hy = camera.heading.tolist()
    return max([0.0] + [x * hx + y * hy for x, y in pts])


def _isosceles(apex: np.ndarray, axis: np.ndarray, tan_half: float, height: float) -> np.ndarray:
    """Counter-clockwise ``(apex, far-right, far-left)`` of a triangle of given axis height."""
    side = np.array([axis[1], -axis[0]])  # right of the axis (axis rotated clockwise)
    far = apex + height * axis
    half = height * tan_half
    return np.stack([apex, far + half * side, far - half * side])


def view_triangle(
    camera: Camera, reach: float | None = None, zrange: tuple[float, float] | None = None
) -> np.ndarray:
    """Qiu's projected view frustum: ``(3, 2)`` apex, far-right, far-left (ccw), legs ``R``.

    ``zrange``: the terrain's heights, for :func:`qiu_reach` (a camera looking up reaches the
    ground only where its frustum does); empty ``(0, 2)`` when the frustum meets no ground.
    """
    if reach is None:
        r = qiu_reach(camera, zrange)
        if r == 0.0:
            return np.zeros((0, 2))
    else:
        r = float(reach)
    if not (math.isfinite(r) and r > 0.0):
        raise FrustumError(f"reach must be a positive finite length, got {reach}")
    cos_h = math.cos(math.atan(camera.tan_half_x))
    return _isosceles(camera.eye[:2], camera.heading, camera.tan_half_x, r * cos_h)


def extension_push(camera: Camera, velocity: np.ndarray, fps: float) -> float:
    """Qiu's Eq. 8 on the ground plane: ``S = V cos(a) / f`` if ``a < pi/2`` else 0.

    ``V`` is the horizontal speed, ``a`` the angle between the horizontal motion and the
    horizontal view direction, ``f`` the frame rate: the triangle's advance in one frame.
    """
    v = np.asarray(velocity, dtype=np.float64)
    if v.shape not in ((2,), (3,)) or not np.isfinite(v).all():
        raise FrustumError(f"velocity must be 2 or 3 finite numbers, got {velocity!r}")
    try:
        rate = float(fps)
    except (TypeError, ValueError):
        rate = math.nan
    if not (math.isfinite(rate) and rate > 0.0):
        raise FrustumError(f"fps must be a positive frame rate, got {fps!r}")
    speed = math.hypot(v[0], v[1])
    if speed == 0.0:
        return 0.0
    cos_a = float(np.dot(v[:2], camera.heading)) / speed
    a = math.acos(max(-1.0, min(1.0, cos_a)))
    return speed * math.cos(a) / rate if a < math.pi / 2 else 0.0


def extension_triangle(
    camera: Camera,
    L: float,
    *,
    velocity: np.ndarray = (0.0, 0.0, 0.0),
    fps: float = 30.0,
    reach: float | None = None,
) -> np.ndarray:
    """Qiu's frustum extension ``(3, 2)``: apex moved back by ``L``, far side out by ``S``.

    Qiu uses ``L`` = one block edge (:func:`block_edge`). The paper's "distance from A to the
    hypotenuse is L+R+S" treats ``R`` as the triangle's height; we use the height of
    :func:`view_triangle`, ``h = R cos(half FOV x)``, so the extension (height ``L + h + S``,
    same apex angle) contains the view triangle and reaches exactly ``S`` beyond it.
    """
    real = isinstance(L, int | float | np.integer | np.floating) and not isinstance(L, bool)
    if not (real and 0.0 <= L < math.inf):
        raise FrustumError(f"L must be a finite length >= 0, got {L!r}")
    tri = view_triangle(camera, reach)
    axis = camera.heading
    height = float(np.dot(0.5 * (tri[1] + tri[2]) - tri[0], axis))
    s = extension_push(camera, velocity, fps)
    return _isosceles(tri[0] - L * axis, axis, camera.tan_half_x, L + height + s)


# --- Jung & Han's hull ------------------------------------------------------------------------


def frustum_hull(camera: Camera, zrange: tuple[float, float] | None = None) -> np.ndarray:
    """Jung & Han: ccw convex hull of the frustum corners projected on the ground.

    With ``zrange=(zlo, zhi)`` the frustum is first clipped to that slab of heights (exact for
    terrain inside it); the result is empty ``(0, 2)`` when the frustum misses the slab.
    """
    if zrange is None:
        pts = [(x, y) for x, y, _ in camera.frustum_corners_rel()]
    else:
        pts = _slab_points(camera, zrange)
    return convex_hull(np.array(pts, dtype=np.float64).reshape(-1, 2)) + camera.eye[:2]


def _slab_points(camera: Camera, zrange: tuple[float, float]) -> list[tuple[float, float]]:
    """``(x, y)`` relative to the eye of the frustum corners within the slab of heights
    ``zrange`` and of its edges' crossings of the slab's planes: the frustum clipped to the
    slab is their convex hull (none: the frustum misses the slab)."""
    rel = camera.frustum_corners_rel()
    zlo, zhi = (float(z) for z in zrange)
    if not (math.isfinite(zlo) and math.isfinite(zhi) and zlo <= zhi):
        raise FrustumError(f"zrange must be finite (zlo, zhi) with zlo <= zhi, got {zrange}")
    zlo -= float(camera.position[2])
    zhi -= float(camera.position[2])
    pts = [(x, y) for x, y, z in rel if zlo <= z <= zhi]
    for z0 in (zlo, zhi):
        for i, j in _EDGE_PAIRS:
            (ax, ay, az), (bx, by, bz) = rel[i], rel[j]
            da, db = az - z0, bz - z0
            if da * db < 0.0:
                t = da / (da - db)
                pts.append((ax + t * (bx - ax), ay + t * (by - ay)))
    return pts


# --- blocks -----------------------------------------------------------------------------------


def block_edge(grid: BlockGrid) -> float:
    """One block edge in world units, ``grid.step * grid.dx`` (Qiu's default ``L``)."""
    return grid.step * grid.dx


def candidate_window(poly: np.ndarray, grid: BlockGrid) -> tuple[int, int, int, int] | None:
    """``(r0, r1, c0, c1)``: the inclusive block rows/columns around a polygon's bounding box
    (one block of margin, clipped to the grid), or ``None`` when none is left."""
    if len(poly) == 0:
        return None
    ex, ey = grid.step * grid.dx, grid.step * grid.dy
    xs, ys = poly[:, 0].tolist(), poly[:, 1].tolist()  # a few vertices: floats beat numpy here
    c0 = math.floor((min(xs) - grid.x0) / ex) - 1
    c1 = math.floor((max(xs) - grid.x0) / ex) + 1
    r0 = math.floor((grid.y0 - max(ys)) / ey) - 1
    r1 = math.floor((grid.y0 - min(ys)) / ey) + 1
    c0, c1 = max(c0, 0), min(c1, grid.cols - 1)
    r0, r1 = max(r0, 0), min(r1, grid.rows - 1)
    return None if c0 > c1 or r0 > r1 else (r0, r1, c0, c1)


def blocks_meeting(polygon: np.ndarray, grid: BlockGrid) -> np.ndarray:
    """``(m, 2)`` int64 ``(br, bc)`` of the blocks whose bounds meet the polygon, row-major."""
    poly = as_polygon(polygon)
    win = candidate_window(poly, grid)
    if win is None:
        return np.zeros((0, 2), dtype=np.int64)
    r0, r1, c0, c1 = win
    br, bc = np.meshgrid(np.arange(r0, r1 + 1), np.arange(c0, c1 + 1), indexing="ij")
    br, bc = br.ravel(), bc.ravel()
    hit = polygon_meets_rects(poly, *grid.block_bounds(br, bc))
    return np.stack([br[hit], bc[hit]], axis=1).astype(np.int64)


def visible_sets(
    camera: Camera,
    grid: BlockGrid,
    *,
    velocity: np.ndarray = (0.0, 0.0, 0.0),
    fps: float = 30.0,
    L: float | None = None,
    culling: str = "qiu",
    zrange: tuple[float, float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Qiu's block sets ``(M, N)``: meeting the frustum, and ``M`` plus those meeting the
    extension; ``N - M`` is to prefetch. ``culling`` is "qiu" (triangle) or "hull"."""
    if culling == "qiu":
        view = view_triangle(camera, zrange=zrange)
    elif culling == "hull":
        view = frustum_hull(camera, zrange)
    else:
        raise FrustumError(f"culling must be 'qiu' or 'hull', got {culling!r}")
    m = blocks_meeting(view, grid)
    ext = extension_triangle(
        camera, block_edge(grid) if L is None else L, velocity=velocity, fps=fps
    )
    n = np.unique(np.concatenate([m, blocks_meeting(ext, grid)]), axis=0)
    return m, n
