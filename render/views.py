"""Cameras for the renderer's commands (pure): the default oblique overview, a nadir view, and
parsing of ``x,y,z`` triples."""

from __future__ import annotations

import math

import numpy as np

from render.errors import CameraSpecError
from streamer.camera import Camera
from streamer.errors import CameraError
from tiler.store import TerrainStore


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


def _zrange(store: TerrainStore) -> tuple[float, float]:
    idx = store.index
    lo, hi = float(np.nanmin(idx.zmin)), float(np.nanmax(idx.zmax))
    return lo, hi


def overview_camera(store: TerrainStore, size: tuple[int, int], fov: float = 45.0) -> Camera:
    """An oblique view of the whole DEM from the south, pitched 35 degrees down."""
    x0, y0, x1, y1 = store.grid.extent
    zlo, zhi = _zrange(store)
    cx, cy, cz = 0.5 * (x0 + x1), 0.5 * (y0 + y1), 0.5 * (zlo + zhi)
    radius = 0.5 * math.hypot(x1 - x0, y1 - y0)
    aspect = size[0] / size[1]
    half = math.radians(fov) / 2
    fit = min(math.tan(half), math.tan(half) * aspect)
    dist = radius / fit * 1.05
    pitch = math.radians(35.0)
    eye = (cx, cy - dist * math.cos(pitch), cz + dist * math.sin(pitch))
    return _camera(eye, (cx, cy, cz), size, fov, dist + 2 * radius)


def nadir_camera(
    store: TerrainStore,
    size: tuple[int, int],
    centre: tuple[float, float],
    height: float,
    fov: float = 45.0,
) -> Camera:
    """Looking straight down from ``height`` above the terrain's top at ``centre``."""
    _, zhi = _zrange(store)
    try:
        return Camera(
            (centre[0], centre[1], zhi + height),
            yaw=0.0,
            pitch=-90.0,
            fov_y=fov,
            viewport=size,
            near=max(0.5, 0.01 * height),
            far=height * 4 + (zhi - _zrange(store)[0]) * 2,
        )
    except CameraError as exc:
        raise CameraSpecError("{detail}", detail=str(exc)) from exc


def _camera(eye, target, size, fov, reach) -> Camera:
    try:
        return Camera.look_at(
            eye, target, viewport=size, fov_y=fov, near=max(0.5, reach * 1e-4), far=reach * 1.5
        )
    except CameraError as exc:
        raise CameraSpecError("{detail}", detail=str(exc)) from exc


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
    ``yaw``/``pitch`` (default: the overview); :class:`CameraSpecError` names these parameters."""
    if position is None:
        if look_at is not None or yaw is not None or pitch is not None:
            raise CameraSpecError("{look_at}/{yaw}/{pitch} need {position} x,y,z")
        return overview_camera(store, size, fov)
    eye = parse_triple(position, "position")
    x0, y0, x1, y1 = store.grid.extent
    zlo, zhi = _zrange(store)
    reach = (
        math.hypot(x1 - x0, y1 - y0)
        + math.hypot(eye[0] - 0.5 * (x0 + x1), eye[1] - 0.5 * (y0 + y1))
        + abs(eye[2] - zlo)
    )
    if look_at is not None:
        if yaw is not None or pitch is not None:
            raise CameraSpecError("give either {look_at} or {yaw}/{pitch}, not both")
        return _camera(eye, parse_triple(look_at, "look_at"), size, fov, reach)
    try:
        return Camera(
            eye,
            yaw=yaw or 0.0,
            pitch=-30.0 if pitch is None else pitch,
            fov_y=fov,
            viewport=size,
            near=max(0.5, reach * 1e-4),
            far=reach * 1.5,
        )
    except CameraError as exc:
        raise CameraSpecError("{detail}", detail=str(exc)) from exc
