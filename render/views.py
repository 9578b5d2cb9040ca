"""Cameras for the renderer's commands (pure): the default overview, a nadir view, the near
plane that follows the camera's clearance above the terrain, and parsing of ``x,y,z`` triples.

Depth precision (docs/RENDER.md, "Precision and extremes"): the fragment shaders write a
logarithmic depth, so a near plane of a few centimetres and a far plane of 1,000 km coexist;
the near plane is therefore chosen from the camera's clearance (:func:`near_plane`), not from
the scene's size."""

from __future__ import annotations

import logging
import math

import numpy as np

from render.errors import CameraSpecError
from streamer.camera import Camera
from streamer.clip import MIN_NEAR, clipped_by_near, ground_clearance, near_plane, near_reach
from streamer.clip import reach as scene_reach
from streamer.clip import zrange as _zrange
from streamer.errors import CameraError
from tiler.grid import BlockGrid
from tiler.store import TerrainStore

log = logging.getLogger(__name__)

#: elongation (long / short horizontal side) beyond which the overview looks along the DEM
STRIP_RATIO = 4.0
#: the overview looks down more steeply than its 35° (20° for a strip) when the DEM's relief
#: seen at that pitch (relief × cos pitch) exceeds this many times its longer horizontal side
#: (framing the tall box can leave the terrain a sliver narrower than a pixel) ...
STEEP_RATIO = 2.0
#: ... and when that framing leaves the image of its footprint under this many pixels across
STEEP_MIN_PX = 4.0


def parse_triple(text: str, name: str) -> tuple[float, float, float]:
    """``"1,2,3"`` → ``(1.0, 2.0, 3.0)``; a clear error naming parameter ``name`` otherwise."""
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        vals = ()
    if len(vals) != 3 or not all(math.isfinite(v) for v in vals):
        template = "{" + name + "} must be three numbers x,y,z, got {got}"
        raise CameraSpecError(template, got=repr(text))
    return vals  # type: ignore[return-value]


#: the renderer passes the camera's cell to the shaders as 32-bit ints (``cam_cell``)
CAMERA_CELL_LIMIT = 2**31 - 1


def camera_cells(grid: BlockGrid, x: float, y: float) -> float:
    """How many cells the point ``(x, y)`` lies from the grid's origin, the larger of the two
    axes (the renderer's ``cam_cell`` must stay within :data:`CAMERA_CELL_LIMIT`)."""
    return max(abs((x - grid.x0) / grid.dx), abs((grid.y0 - y) / grid.dy))


def _tan_half_diag(size: tuple[int, int], fov: float) -> float:
    t = math.tan(math.radians(fov) / 2)
    return t * math.hypot(1.0, size[0] / size[1])


def overview_camera(store: TerrainStore, size: tuple[int, int], fov: float = 45.0) -> Camera:
    """A view of the whole DEM above its highest point: from the south pitched 35° down, or,
    for a DEM more than :data:`STRIP_RATIO` times longer than wide, from beyond its south or
    west end looking along it (pitched 20° down) so a thin strip is not a sub-pixel line; a DEM
    whose relief dwarfs its extent (:data:`STEEP_RATIO`), which that framing of its tall box
    would shrink to under :data:`STEEP_MIN_PX` pixels, is seen from more steeply above (up to
    straight down) at its centre."""
    x0, y0, x1, y1 = store.grid.extent
    zlo, zhi = _zrange(store)
    w, h = max(x1 - x0, 1e-9), max(y1 - y0, 1e-9)
    along_x = w > STRIP_RATIO * h
    strip = along_x or h > STRIP_RATIO * w
    pitch = math.radians(20.0 if strip else 35.0)
    eye, far, dist = _overview_eye(store, size, fov, pitch, along_x, strip)
    side, relief = max(w, h), zhi - zlo
    if relief * math.cos(pitch) > STEEP_RATIO * side:  # the relief may shrink the terrain:
        across, depth = (h, w) if along_x else (w, h)  # its footprint's image, in pixels
        focal = (size[1] / 2) / math.tan(math.radians(fov) / 2)
        if focal * min(across, depth * math.sin(pitch)) / dist < STEEP_MIN_PX:
            pitch = math.acos(STEEP_RATIO * side / relief)  # the relief seen no taller than
            eye, far, _ = _overview_eye(store, size, fov, pitch, along_x, False, side)  # that
    near = near_plane(store, tuple(eye), _tan_half_diag(size, fov), max(0.5, 1e-4 * far))
    try:
        return Camera(
            tuple(eye), yaw=90.0 if along_x else 0.0, pitch=-math.degrees(pitch), fov_y=fov,
            viewport=size, near=near, far=max(far, 2 * near),
        )  # fmt: skip
    except CameraError as exc:
        raise CameraSpecError("{detail}", detail=str(exc)) from exc


def _overview_eye(
    store: TerrainStore,
    size: tuple[int, int],
    fov: float,
    pitch: float,
    along_x: bool,
    strip: bool,
    margin_cap: float = math.inf,
) -> tuple[np.ndarray, float, float]:
    """:func:`overview_camera`'s eye, far distance and distance to its target (the DEM's box's
    centre, or a strip's near end) at ``pitch`` (radians); the eye's margin above the DEM's top
    (5 % of its relief) is at most ``margin_cap`` (but 2 cells and 1 m at least)."""
    x0, y0, x1, y1 = store.grid.extent
    zlo, zhi = _zrange(store)
    heading = np.array([1.0, 0.0]) if along_x else np.array([0.0, 1.0])
    fwd = np.array([heading[0] * math.cos(pitch), heading[1] * math.cos(pitch), -math.sin(pitch)])
    right = np.array([heading[1], -heading[0], 0.0])
    up = np.cross(right, fwd)
    cx, cy, cz = 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (zlo + zhi)
    if strip:  # aim at the near end: the far end then lies near the horizon, in view
        target = np.array([x0, cy, cz]) if along_x else np.array([cx, y0, cz])
    else:
        target = np.array([cx, cy, cz])
    ty = math.tan(math.radians(fov) / 2) * 0.95
    tx = ty * size[0] / size[1]
    corners = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (zlo, zhi)])
    rel = corners - target
    along, sx, sy = rel @ fwd, rel @ right, rel @ up
    dist = float(np.max(np.maximum(np.abs(sx) / tx, np.abs(sy) / ty) - along))
    margin = max(min(0.05 * (zhi - zlo), margin_cap), 2.0 * max(store.grid.dx, store.grid.dy), 1.0)
    dist = max(dist, (zhi + margin - target[2]) / math.sin(pitch), 1.0)
    eye = target - dist * fwd
    far = float(np.max((corners - eye) @ fwd)) * 1.5 + 1.0
    return eye, far, dist


def nadir_camera(
    store: TerrainStore,
    size: tuple[int, int],
    centre: tuple[float, float],
    height: float,
    fov: float = 45.0,
) -> Camera:
    """Looking straight down from ``height`` above the terrain's top at ``centre``."""
    zlo, zhi = _zrange(store)
    try:
        return Camera(
            (centre[0], centre[1], zhi + height),
            yaw=0.0,
            pitch=-90.0,
            fov_y=fov,
            viewport=size,
            near=max(MIN_NEAR, min(0.5 * height, max(0.5, 0.01 * height))),
            far=height * 4 + (zhi - zlo) * 2,
        )
    except CameraError as exc:
        raise CameraSpecError("{detail}", detail=str(exc)) from exc


def _camera(store, eye, target, size, fov, reach) -> Camera:
    near = near_plane(store, eye, _tan_half_diag(size, fov), max(0.5, reach * 1e-4))
    try:
        return Camera.look_at(eye, target, viewport=size, fov_y=fov, near=near, far=reach * 1.5)
    except CameraError as exc:
        raise CameraSpecError("{detail}", detail=str(exc)) from exc


def warn_below_ground(
    store: TerrainStore, eye: tuple[float, float, float], camera: Camera | None = None
) -> float:
    """Log a warning when ``eye`` is below the terrain under it (the full-resolution surface,
    :func:`streamer.clip.ground_height`: the view then shows the terrain from below) and, given
    the ``camera``, when it is on or above the ground but closer to it than its near plane
    reaches (:func:`streamer.clip.clipped_by_near`: the near plane clips the ground in front
    of it), naming the clearance; how far below (0: not, or unknown). Reads a block only when
    the eye is under its block's highest point (plus the near plane's reach)."""
    within = near_reach(camera) if camera is not None else 0.0
    clearance = ground_clearance(store, np.array([eye], dtype=np.float64), within)
    c = float(clearance[0])
    if c < 0:
        log.warning(
            "the camera at z = %.1f m is %.1f m below the terrain under it (at least %.1f m at "
            "x %.1f, y %.1f): the view shows the terrain from below; raise the camera above "
            "the ground",
            eye[2], -c, eye[2] - c, eye[0], eye[1],
        )  # fmt: skip
        return -c
    if camera is not None and clipped_by_near(clearance, [camera])[0]:
        log.warning(
            "the camera at z = %.3f m is %s the terrain under it (the ground at %.3f m at x "
            "%.1f, y %.1f), "
            "closer than its %.3g m near plane reaches (%.3g m): the near plane clips the "
            "ground in front of it, so the view shows sky or nothing where the terrain is; "
            "raise the camera at least %.3g m above the ground",
            eye[2], "on" if c == 0 else f"only {c:.3g} m above", eye[2] - c, eye[0], eye[1],
            camera.near, near_reach(camera), near_reach(camera),
        )  # fmt: skip
    return 0.0


def ground_note(store: TerrainStore, camera: Camera) -> str:
    """Why ``camera`` may see no terrain because of where it is: ``""``, or a clause naming
    its depth below the terrain under it or its clearance above it when that is less than its
    near plane reaches (for a "no terrain pixel" error; no warning is logged)."""
    reach_ = near_reach(camera)
    c = float(ground_clearance(store, np.array([camera.position], dtype=np.float64), reach_)[0])
    return clearance_note(camera, c)


def clearance_note(camera: Camera, clearance: float) -> str:
    """:func:`ground_note`'s clause for ``camera`` given its ``clearance`` above the terrain
    under it (:func:`streamer.clip.ground_clearance`; NaN: unknown, ``inf``: high above)."""
    c, reach_ = clearance, near_reach(camera)
    if c < 0:
        return (
            f"the camera is {-c:.3g} m below the terrain under it (it sees the terrain from "
            "below, or nothing); raise it above the ground"
        )
    if clipped_by_near([c], [camera])[0]:
        where = "on" if c == 0 else f"only {c:.3g} m above"
        return (
            f"the camera is {where} the terrain under it, closer than its {camera.near:.3g} m "
            f"near plane reaches ({reach_:.3g} m): the near plane clips the ground in front "
            f"of it; raise the camera at least {reach_:.3g} m above the ground"
        )
    return ""


def make_camera(
    store: TerrainStore,
    size: tuple[int, int],
    *,
    position: str | None = None,
    look_at: str | None = None,
    yaw: float | None = None,
    pitch: float | None = None,
    fov: float = 45.0,
) -> Camera:
    """The camera ``position`` (``"x,y,z"``) looking at ``look_at`` (``"x,y,z"``) or along
    ``yaw``/``pitch`` (default: the overview); :class:`CameraSpecError` names these parameters.
    The near plane follows the camera's clearance above the terrain (:func:`near_plane`)."""
    if position is None:
        if look_at is not None or yaw is not None or pitch is not None:
            raise CameraSpecError("{look_at}/{yaw}/{pitch} need {position} x,y,z")
        return overview_camera(store, size, fov)
    eye = parse_triple(position, "position")
    g = store.grid
    if camera_cells(g, eye[0], eye[1]) > CAMERA_CELL_LIMIT - 2:
        far = CAMERA_CELL_LIMIT * min(abs(g.dx), abs(g.dy))
        raise CameraSpecError(
            "{position} {got} lies more than 2^31 cells from the DEM's origin, beyond the "
            "renderer's 32-bit cell index; put the camera within {far} m of the DEM",
            got=position,
            far=f"{far:.3g}",
        )
    reach = scene_reach(store, eye)
    if look_at is not None:
        if yaw is not None or pitch is not None:
            raise CameraSpecError("give either {look_at} or {yaw}/{pitch}, not both")
        cam = _camera(store, eye, parse_triple(look_at, "look_at"), size, fov, reach)
        warn_below_ground(store, eye, cam)  # once the camera is valid
        return cam
    near = near_plane(store, eye, _tan_half_diag(size, fov), max(0.5, reach * 1e-4))
    try:
        cam = Camera(
            eye,
            yaw=yaw or 0.0,
            pitch=-30.0 if pitch is None else pitch,
            fov_y=fov,
            viewport=size,
            near=near,
            far=reach * 1.5,
        )
    except CameraError as exc:
        raise CameraSpecError("{detail}", detail=str(exc)) from exc
    warn_below_ground(store, eye, cam)
    return cam


def terrain_cells(store: TerrainStore) -> bool:
    """Whether some cell of the DEM has four terrain corners: only such cells are drawn (a
    triangle with a nodata corner is not); reads the masks of blocks with nodata, and only
    until one such cell is found."""
    idx = store.index
    exists = np.asarray(idx.exists, dtype=bool)
    nodata = np.asarray(idx.has_nodata, dtype=bool)
    if (exists & ~nodata).any():  # (a block without nodata or padding: every cell is terrain)
        return True
    for br, bc in zip(*np.nonzero(exists), strict=True):
        m = store.read_mask((int(br), int(bc)))
        if (m[:-1, :-1] & m[1:, :-1] & m[:-1, 1:] & m[1:, 1:]).any():
            return True
    return False


#: a view with a side under this many pixels, in which the DEM's image would be at least 2 px
#: a side were the view this size, is "too small to hold a terrain pixel" (no_pixel_cause)
SMALL_VIEW = 16


def image_box(store: TerrainStore, camera: Camera) -> tuple[float, float, float, float] | None:
    """The pixel rectangle ``(left, top, right, bottom)`` bounding the DEM's box (its extent
    times its height range) as ``camera`` sees it; None when part of the box is level with or
    behind the camera (no finite bound)."""
    x0, y0, x1, y1 = store.grid.extent
    zlo, zhi = _zrange(store)
    corners = np.array([[x, y, z] for x in (x0, x1) for y in (y0, y1) for z in (zlo, zhi)])
    px, py, depth = camera.project(corners)
    if not np.all(depth > 0.0):
        return None
    return float(px.min()), float(py.min()), float(px.max()), float(py.max())


def no_pixel_cause(store: TerrainStore, camera: Camera) -> tuple[str, str]:
    """Why a view whose triangles drew no terrain pixel shows none, as ``(kind, clause)``:
    ``"nodata"`` (no cell of the DEM has four terrain corners), ``"size"`` (the DEM's image
    fills a view too small to hold a terrain pixel), ``"steep"`` (its image is a sliver narrower
    than a pixel: relief far beyond its extent, or seen edge-on), ``"far"`` (its image is
    smaller than a pixel), ``"outside"`` (its image lies outside the view) or ``("", "")`` when
    none of these is certain. The clause names the values and what to do, without flags."""
    if not terrain_cells(store):
        return "nodata", (
            "no cell of the DEM has four terrain corners, so its terrain is too sparse to "
            "draw from any camera (a triangle with a nodata corner is not drawn); check the "
            "DEM's nodata value and mask"
        )
    box = image_box(store, camera)
    if box is None:
        return "", ""
    w, h = camera.viewport
    left, top, right, bottom = box
    bw, bh = right - left, bottom - top
    size = f"{bw:.2g} x {bh:.2g} px"
    if right <= 0.0 or bottom <= 0.0 or left >= w or top >= h:
        return "outside", (
            f"the DEM's image ({size}) lies outside the {w}x{h} view; point the camera at "
            "the terrain"
        )
    if min(w, h) < SMALL_VIEW and min(bw, bh) * SMALL_VIEW / min(w, h) >= 2.0:
        return "size", (
            f"the {w}x{h} view is too small to hold a terrain pixel: the DEM's image "
            f"({size}) covers none of its pixel centres; render a larger view (at least "
            f"{SMALL_VIEW}x{SMALL_VIEW})"
        )
    if min(bw, bh) < 2.0 and max(bw / w, bh / h) >= 0.25:
        x0, y0, x1, y1 = store.grid.extent
        zlo, zhi = _zrange(store)
        side = max(x1 - x0, y1 - y0)
        why = (
            f"its {zhi - zlo:.3g} m relief is {(zhi - zlo) / side:.3g} times its "
            f"{side:.3g} m extent, so"
            if zhi - zlo > STEEP_RATIO * side
            else "it is seen edge-on, so"
        )
        return "steep", (
            f"{why} the DEM's image is a sliver ({size}) narrower than a pixel; look down on "
            "it from more steeply above (or use the default overview camera)"
        )
    if bw < 1.0 and bh < 1.0:
        return "far", (
            f"the DEM's image is {size}, smaller than a pixel: the DEM is too far from the "
            "camera to be seen; move the camera closer"
        )
    return "", ""
