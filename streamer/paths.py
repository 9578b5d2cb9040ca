"""Deterministic fly-through paths: lists of :class:`~streamer.camera.Camera`, one per frame.

Every function takes ``**camera_kw`` (``fov_y``, ``viewport``, ``near``, ``far``) passed on to
each camera. Yaw is in degrees clockwise from north, pitch negative looks down (see
:mod:`streamer.camera`). Paths hold no clock: frame ``i`` is simply the ``i``-th camera.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path

import numpy as np

from streamer.camera import Camera
from streamer.errors import KeyframeError, PathError
from tiler.grid import BlockGrid

KEYFRAME_FIELDS = ("t", "x", "y", "z", "yaw", "pitch")
LINE = "__line__"  # a CSV record's line in its file, for the messages


def _count(name: str, value: int) -> int:
    """A positive integer, or raise ``PathError`` naming it."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise PathError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def _num(name: str, value: float, *, positive: bool = False, nonneg: bool = False) -> float:
    """A finite float (optionally > 0 or >= 0), or raise ``PathError`` naming it."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise PathError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or (positive and v <= 0.0) or (nonneg and v < 0.0):
        need = "> 0" if positive else ">= 0" if nonneg else "finite"
        raise PathError(f"{name} must be finite and {need}, got {value!r}")
    return v


def _vec(name: str, value: object, n: int) -> np.ndarray:
    """A finite float64 vector of length ``n``, or raise ``PathError`` naming it."""
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise PathError(f"{name} must be {n} numbers, got {value!r}") from None
    if a.shape != (n,) or not np.isfinite(a).all():
        raise PathError(f"{name} must be {n} finite numbers, got {value!r}")
    return a


def _bearing(dx: float, dy: float) -> float:
    """Yaw (degrees clockwise from north, in [0, 360)) of a horizontal direction; 0 if none."""
    return math.degrees(math.atan2(dx, dy)) % 360.0 if (dx or dy) else 0.0


def _params(frames: int) -> np.ndarray:
    """``frames`` values from 0 to 1 inclusive (just 0 for one frame)."""
    return np.linspace(0.0, 1.0, frames) if frames > 1 else np.zeros(1)


def line(
    start: Iterable[float],
    end: Iterable[float],
    frames: int,
    *,
    pitch: float = -20.0,
    yaw: float | None = None,
    **camera_kw: object,
) -> list[Camera]:
    """Constant-speed straight flight from ``start`` to ``end`` (both included, world xyz).

    Looks along the horizontal direction of travel (or ``yaw``), ``pitch`` degrees.
    """
    n = _count("frames", frames)
    a, b = _vec("start", start, 3), _vec("end", end, 3)
    heading = _bearing(b[0] - a[0], b[1] - a[1]) if yaw is None else _num("yaw", yaw)
    pos = a + _params(n)[:, None] * (b - a)
    return [Camera(tuple(p), yaw=heading, pitch=pitch, **camera_kw) for p in pos]  # type: ignore[arg-type]


def circle(
    center: Iterable[float],
    radius: float,
    height: float,
    frames: int,
    *,
    look: str = "inward",
    pitch: float = -25.0,
    start_bearing: float = 0.0,
    clockwise: bool = True,
    **camera_kw: object,
) -> list[Camera]:
    """One full loop at ``height`` around ``center`` ``(x, y)``, the last frame before the first.

    The camera starts at ``start_bearing`` (degrees from north as seen from the centre) and moves
    clockwise (seen from above) by default. ``look="inward"`` faces the centre's vertical axis;
    ``look="tangent"`` faces the direction of travel.
    """
    n = _count("frames", frames)
    c = _vec("center", center, 2)
    r = _num("radius", radius, positive=True)
    z = _num("height", height)
    if look not in ("inward", "tangent"):
        raise PathError(f"look must be 'inward' or 'tangent', got {look!r}")
    sign = 1.0 if clockwise else -1.0
    bearings = _num("start_bearing", start_bearing) + sign * 360.0 * np.arange(n) / n
    out = []
    for phi in bearings:
        t = math.radians(phi)
        yaw = phi + 180.0 if look == "inward" else phi + sign * 90.0
        pos = (c[0] + r * math.sin(t), c[1] + r * math.cos(t), z)
        out.append(Camera(pos, yaw=yaw % 360.0, pitch=pitch, **camera_kw))  # type: ignore[arg-type]
    return out


def canyon(
    height_fn: Callable[[float, float], float],
    start: Iterable[float],
    end: Iterable[float],
    frames: int,
    clearance: float,
    *,
    pitch: float = -10.0,
    **camera_kw: object,
) -> list[Camera]:
    """Terrain-following flight from ``start`` to ``end`` ``(x, y)``, ``clearance`` above ground.

    ``height_fn(x, y) -> z`` gives the ground height (called with floats, once per frame); the
    camera looks along the direction of travel at ``pitch`` degrees.
    """
    n = _count("frames", frames)
    a, b = _vec("start", start, 2), _vec("end", end, 2)
    gap = _num("clearance", clearance, nonneg=True)
    heading = _bearing(b[0] - a[0], b[1] - a[1])
    out = []
    for x, y in a + _params(n)[:, None] * (b - a):
        g = height_fn(float(x), float(y))
        try:
            z = float(g)
        except (TypeError, ValueError):
            raise PathError(f"height_fn({x}, {y}) must return a number, got {g!r}") from None
        if not math.isfinite(z):
            raise PathError(f"height_fn({x}, {y}) returned a non-finite height {g!r}")
        out.append(Camera((x, y, z + gap), yaw=heading, pitch=pitch, **camera_kw))  # type: ignore[arg-type]
    return out


def teleports(
    bounds: Iterable[float],
    frames: int,
    seed: int,
    every: int,
    *,
    pitch_range: tuple[float, float] = (-60.0, -10.0),
    **camera_kw: object,
) -> list[Camera]:
    """Random jumps: a new uniform pose every ``every`` frames, held in between.

    ``bounds`` = ``(xmin, ymin, zmin, xmax, ymax, zmax)`` (GeoJSON 3-D bbox order) for the
    position; yaw is uniform in [0, 360), pitch uniform in ``pitch_range``. Same seed, same path.
    """
    n = _count("frames", frames)
    k = _count("every", every)
    bb = _vec("bounds", bounds, 6)
    lo, hi = bb[:3], bb[3:]
    if not (lo <= hi).all():
        raise PathError(f"bounds must be (xmin, ymin, zmin, xmax, ymax, zmax), got {bb.tolist()}")
    p0, p1 = (_num("pitch_range", p) for p in pitch_range)
    if not -90.0 <= p0 <= p1 <= 90.0:
        raise PathError(f"pitch_range must be (low, high) within [-90, 90], got {pitch_range}")
    rng = np.random.default_rng(seed)
    jumps = -(-n // k)
    pos = lo + rng.random((jumps, 3)) * (hi - lo)
    yaw = rng.random(jumps) * 360.0
    pitch = p0 + rng.random(jumps) * (p1 - p0)
    return [
        Camera(tuple(pos[i // k]), yaw=yaw[i // k], pitch=pitch[i // k], **camera_kw)  # type: ignore[arg-type]
        for i in range(n)
    ]


# --- keyframes --------------------------------------------------------------------------------


def read_keyframes(path: str | Path) -> list[dict[str, object]]:
    """Keyframe records from a ``.json`` or ``.csv`` file (see :func:`keyframes`)."""
    p = Path(path)
    try:  # (utf-8-sig: a spreadsheet's "CSV UTF-8" starts with a byte-order mark)
        text = p.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as e:
        raise KeyframeError(
            f"{p}: not UTF-8 text (byte {e.start} is {e.object[e.start : e.start + 1]!r}); "
            "save it as UTF-8"
        ) from None
    if p.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise KeyframeError(f"{p}: not valid JSON ({e})") from None
        if not isinstance(data, list) or not all(isinstance(r, Mapping) for r in data):
            raise KeyframeError(f"{p}: JSON keyframes must be a list of objects")
        return [dict(r) for r in data]
    if p.suffix.lower() == ".csv":
        rows = csv.DictReader(text.splitlines())
        out: list[dict[str, object]] = []
        for r in rows:
            if None in r:  # more fields than the header names
                raise KeyframeError(
                    f"{p}: line {rows.line_num} has {len(r) - 1 + len(r[None])} fields, the "
                    f"header {len(rows.fieldnames or ())}"
                )
            out.append({(k or "").strip(): v for k, v in r.items()} | {LINE: rows.line_num})
        return out
    raise KeyframeError(f"{p}: keyframe files must end in .json or .csv, got {p.suffix!r}")


def _lerp_angle(a: np.ndarray, b: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Shortest-way interpolation of angles in degrees, result in [0, 360)."""
    d = (b - a + 180.0) % 360.0 - 180.0
    return (a + u * d) % 360.0


def keyframes_from_records(
    records: Iterable[Mapping[str, object]], frames: int, **camera_kw: object
) -> list[Camera]:
    """Cameras at ``frames`` evenly spaced times from the first to the last keyframe.

    Linear in position, pitch and roll; yaw (and roll) turn the shorter way round.
    """
    n = _count("frames", frames)
    recs = list(records)
    if not recs:
        raise KeyframeError("keyframes need at least one record")
    cols: dict[str, list[float]] = {f: [] for f in (*KEYFRAME_FIELDS, "roll")}
    for i, r in enumerate(recs):
        name = f"keyframe {i}" + (f" (line {r[LINE]})" if LINE in r else "")
        missing = [f for f in KEYFRAME_FIELDS if f not in r]
        if missing:
            raise KeyframeError(f"{name} lacks {missing} (needs {list(KEYFRAME_FIELDS)})")
        for f in cols:
            raw = r.get(f, 0.0) if f == "roll" else r[f]
            try:
                if isinstance(raw, bool):  # (JSON true/false: not 1 and 0)
                    raise TypeError
                v = float(raw)  # type: ignore[arg-type]
            except (TypeError, ValueError):
                raise KeyframeError(f"{name}: {f} must be a number, got {raw!r}") from None
            if not math.isfinite(v):
                raise KeyframeError(f"{name}: {f} must be finite, got {raw!r}")
            if f == "pitch" and not -90.0 <= v <= 90.0:  # (an interpolated one would be named)
                raise KeyframeError(
                    f"{name}: pitch must be within [-90, 90] degrees (negative looks "
                    f"down), got {raw!r}"
                )
            cols[f].append(v)
    a = {f: np.array(v) for f, v in cols.items()}
    t = a["t"]
    if (np.diff(t) <= 0.0).any():
        raise KeyframeError(f"keyframe times must strictly increase, got {t.tolist()}")
    times = t[0] + _params(n) * (t[-1] - t[0])
    j = np.clip(np.searchsorted(t, times, side="right") - 1, 0, max(len(t) - 2, 0))
    j1 = np.minimum(j + 1, len(t) - 1)
    span = t[j1] - t[j]
    u = np.where(span > 0.0, (times - t[j]) / np.where(span > 0.0, span, 1.0), 0.0)

    def lin(f: str) -> np.ndarray:
        return a[f][j] + u * (a[f][j1] - a[f][j])

    xyz = np.stack([lin("x"), lin("y"), lin("z")], axis=1)
    yaw = _lerp_angle(a["yaw"][j], a["yaw"][j1], u)
    roll = (_lerp_angle(a["roll"][j], a["roll"][j1], u) + 180.0) % 360.0 - 180.0
    pitch = lin("pitch")
    return [
        Camera(tuple(xyz[i]), yaw=yaw[i], pitch=pitch[i], roll=roll[i], **camera_kw)  # type: ignore[arg-type]
        for i in range(n)
    ]


def keyframes(path: str | Path, frames: int, **camera_kw: object) -> list[Camera]:
    """Interpolated cameras from a keyframe file.

    JSON: a list of objects ``{"t", "x", "y", "z", "yaw", "pitch"}`` (optional ``"roll"``), e.g.
    ``[{"t": 0, "x": 0, "y": 0, "z": 500, "yaw": 350, "pitch": -20}, ...]``. CSV: a header
    ``t,x,y,z,yaw,pitch`` (optional ``roll`` column) then one row per keyframe. ``t`` (seconds,
    any unit) must strictly increase; frames are spaced evenly from the first to the last ``t``.
    Position, pitch and roll are linear; yaw takes the shorter way (350 -> 10 passes north).
    A bad record is a :class:`KeyframeError` naming the file.
    """
    n = _count("frames", frames)
    records = read_keyframes(path)
    try:
        return keyframes_from_records(records, n, **camera_kw)
    except KeyframeError as exc:
        raise KeyframeError(f"{path}: {exc}") from None


# --- the default fly-through ------------------------------------------------------------------

FLYTHROUGH_PITCH = 25.0  # degrees below the horizon, when the extent is wide enough


def _exit_distance(p: np.ndarray, u: np.ndarray, box: tuple[float, ...]) -> float:
    """Distance from ``p`` inside ``box`` (xmin, ymin, xmax, ymax) along unit ``u`` to its edge."""
    out = math.inf
    for i, (lo, hi) in enumerate(((box[0], box[2]), (box[1], box[3]))):
        if u[i] > 0.0:
            out = min(out, (hi - p[i]) / u[i])
        elif u[i] < 0.0:
            out = min(out, (lo - p[i]) / u[i])
    return max(out, 0.0)


def default_flythrough(
    grid: BlockGrid,
    zmin: float,
    zmax: float,
    frames: int,
    fps: float,
    speed: float | None = None,
    **camera_kw: object,
) -> list[Camera]:
    """A low oblique pass over the store at ``speed`` (default one block edge per second).

    The camera flies clockwise along an ellipse inscribed in the extent (semi-axes 0.3 of its
    width and height, starting south-west) at ``zmax + margin`` (margin = max(10 % of the relief,
    2 % of a block edge)). On stores many blocks wide that is a gently curving pass across (a loop
    takes ~2 pi 0.3 width / speed: ~30 s, 12 degrees/s, 16 blocks wide); small stores are circled
    and turn faster. It looks at a ground point ahead, near the loop a
    quarter round further at most, pitched ~25 degrees down (steeper on small stores): the view
    centre reaches ``zmin`` inside the extent, so every frame sees terrain. Defaults ``near`` =
    margin/20, ``far`` = max(8 block edges, 4x the slant range to that point) unless given.
    """
    n = _count("frames", frames)
    rate = _num("fps", fps, positive=True)
    lo, hi = _num("zmin", zmin), _num("zmax", zmax)
    if lo > hi:
        raise PathError(f"zmin must be <= zmax, got zmin={zmin}, zmax={zmax}")
    edge = grid.step * grid.dx
    v = edge if speed is None else _num("speed", speed, positive=True)
    box = grid.extent
    cx, cy = 0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])
    ax, ay = 0.3 * (box[2] - box[0]), 0.3 * (box[3] - box[1])
    margin = max(0.1 * (hi - lo), 0.02 * edge)
    height = hi + margin
    drop = height - lo

    phi = np.linspace(0.0, 2.0 * math.pi, 4097)
    loop = np.stack([cx + ax * np.sin(phi), cy + ay * np.cos(phi)], axis=1)
    arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(loop, axis=0).T))])
    perimeter = float(arc[-1])
    if v / rate > perimeter:  # each frame a random point of the loop; beyond ~1e16, NaN poses
        raise PathError(
            f"speed {v:g} at {rate:g} fps moves the camera {v / rate:.4g} per frame, more than "
            f"the default path's whole loop ({perimeter:.4g}); pass a speed of at most "
            f"{perimeter * rate:.4g} (world units per second)"
        )
    s0 = float(np.interp(1.25 * math.pi, phi, arc))  # start at bearing 225 (south-west)
    reach = drop / math.tan(math.radians(FLYTHROUGH_PITCH))
    lead = min(reach, 0.25 * perimeter)

    def at(s: np.ndarray) -> np.ndarray:
        p = np.interp(np.mod(s, perimeter), arc, phi)
        return np.stack([cx + ax * np.sin(p), cy + ay * np.cos(p)], axis=-1)

    s = s0 + np.arange(n) * (v / rate)
    cams, targets = at(s), at(s + lead)
    poses = []
    slant_max = 0.0
    for c, t in zip(cams, targets, strict=True):
        d = t - c
        chord = float(np.hypot(*d))
        u = d / chord
        dist = min(reach, max(chord, 0.9 * _exit_distance(c, u, box)))
        poses.append((c, _bearing(u[0], u[1]), -math.degrees(math.atan2(drop, dist))))
        slant_max = max(slant_max, math.hypot(drop, dist))
    kw = dict(camera_kw)
    kw.setdefault("near", margin / 20.0)
    kw.setdefault("far", max(8.0 * edge, 4.0 * slant_max))
    return [Camera((c[0], c[1], height), yaw=y, pitch=p, **kw) for c, y, p in poses]  # type: ignore[arg-type]
