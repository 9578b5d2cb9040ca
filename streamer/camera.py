"""A pinhole camera in the terrain's world frame (pure numpy, float64, no OpenGL).

World frame (as in :mod:`tiler.grid`): ``x`` east, ``y`` north, ``z`` up. Orientation is given by
``yaw`` (degrees clockwise from north seen from above: 0 looks north (+y), 90 looks east (+x)),
``pitch`` (degrees above the horizon: negative looks down, -90 straight down) and ``roll``
(degrees about the view axis: positive banks to the right, i.e. the camera's up vector tilts
towards its right vector). The right vector of an unrolled camera is always horizontal and is
derived from ``yaw`` alone, so looking straight up or down is well defined.

Camera space follows OpenGL: ``x`` = right, ``y`` = up, the camera looks down ``-z``.
:meth:`Camera.view_matrix` is *camera-relative*: its translation part is zero and it must be
applied to ``p - camera.position`` computed in float64 on the CPU. Positions far from the origin
(UTM metres are ~1e6-1e7) then keep their precision when cast to float32 for the GPU.

Pixels: origin at the top-left corner of the viewport, ``x`` right, ``y`` down; the image centre
is ``(width/2, height/2)``. The focal length in pixels is ``(height/2) / tan(fov_y/2)``: we use
the viewport *height* as Qiu et al.'s ``H`` because their ``alpha`` is the vertical field of view
(with the width, ``H/(2 tan(alpha/2))`` would not be a focal length unless the viewport is square).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from streamer.errors import CameraError

Vec3 = tuple[float, float, float]

#: The nearest near plane (metres): the GPU gets ``near`` as a float32, and the depth below
#: ~1e-30 m underflows (a blank image); 1 µm is far below any clearance that matters.
MIN_NEAR_M = 1e-6
#: The farthest far plane (metres): beyond ~1e38 float32 overflows (a blank image).
MAX_FAR_M = 1e15
#: The narrowest vertical field of view (degrees): a subnormal one made ``focal_px`` inf (NaN
#: projections) or divided by zero; the CLI's ``--fov`` starts at 1.
MIN_FOV_Y = 1e-3


def _finite(name: str, value: float) -> float:
    """``value`` as a float, or raise ``CameraError`` naming it."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise CameraError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise CameraError(f"{name} must be finite, got {value!r}")
    return v


def _vec3(name: str, value: object) -> Vec3:
    """A finite 3-vector as a tuple of floats, or raise ``CameraError`` naming it."""
    arr = np.asarray(value, dtype=object)
    if arr.shape != (3,):
        raise CameraError(f"{name} must be 3 numbers (x, y, z), got {value!r}")
    x, y, z = (_finite(f"{name}[{i}]", arr[i]) for i in range(3))
    return x, y, z


def _turn(degrees: float) -> float:
    """An angle reduced to ``(-360, 360)`` degrees exactly (``math.fmod``; unchanged within)."""
    return math.fmod(degrees, 360.0)


def _readonly(a: np.ndarray) -> np.ndarray:
    """Mark an array read-only (cached vectors must not be mutated by callers)."""
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: world position, yaw/pitch/roll in degrees, vertical FOV, viewport."""

    position: Vec3
    yaw: float = 0.0
    pitch: float = 0.0
    roll: float = 0.0
    fov_y: float = 60.0
    viewport: tuple[int, int] = (1024, 768)
    near: float = 1.0
    far: float = 100_000.0

    def __post_init__(self) -> None:
        set_ = object.__setattr__
        set_(self, "position", _vec3("position", self.position))
        for name in ("yaw", "pitch", "roll", "fov_y", "near", "far"):
            set_(self, name, _finite(name, getattr(self, name)))
        if not -90.0 <= self.pitch <= 90.0:
            raise CameraError(f"pitch must be in [-90, 90] degrees, got {self.pitch}")
        if not MIN_FOV_Y <= self.fov_y < 180.0:
            raise CameraError(f"fov_y must be in [{MIN_FOV_Y:g}, 180) degrees, got {self.fov_y!r}")
        vp = tuple(self.viewport) if isinstance(self.viewport, tuple | list) else None
        if vp is None or len(vp) != 2:
            raise CameraError(f"viewport must be (width, height) pixels, got {self.viewport!r}")
        for v in vp:
            whole = isinstance(v, int | np.integer) or (
                isinstance(v, float) and math.isfinite(v) and v == int(v)
            )
            if isinstance(v, bool) or not whole:
                raise CameraError(f"viewport sizes must be integers, got {self.viewport!r}")
            if int(v) < 1:
                raise CameraError(f"viewport sizes must be >= 1 pixel, got {self.viewport!r}")
        set_(self, "viewport", (int(vp[0]), int(vp[1])))
        if not self.near > 0.0:
            raise CameraError(f"near must be > 0, got {self.near}")
        if self.near < MIN_NEAR_M:
            raise CameraError(
                f"near must be at least {MIN_NEAR_M:g} m (float32 depth), got {self.near:g}"
            )
        if not self.far > self.near:
            raise CameraError(f"far must be > near ({self.near}), got {self.far}")
        if self.far > MAX_FAR_M:
            raise CameraError(
                f"far must be at most {MAX_FAR_M:g} m (float32 depth), got {self.far:g}"
            )

    @classmethod
    def look_at(
        cls,
        position: Vec3,
        target: Vec3,
        up: Vec3 = (0.0, 0.0, 1.0),
        **kw: object,
    ) -> Camera:
        """A camera at ``position`` looking at ``target``; roll makes its up closest to ``up``.

        Looking straight up or down gives yaw 0; an ``up`` parallel to the view gives roll 0.
        """
        p = np.array(_vec3("position", position))
        d = np.array(_vec3("target", target)) - p
        n = float(np.linalg.norm(d))
        if not n > 0.0:
            raise CameraError(f"target must differ from position, both are {tuple(p)}")
        d /= n
        hz = math.hypot(d[0], d[1])
        yaw = math.degrees(math.atan2(d[0], d[1])) % 360.0 if hz > 1e-12 else 0.0
        pitch = math.degrees(math.atan2(d[2], hz))
        u = np.array(_vec3("up", up))
        if not np.linalg.norm(u) > 0.0:
            raise CameraError(f"up must be a non-zero vector, got {up!r}")
        plain = cls(position=tuple(p), yaw=yaw, pitch=pitch, **kw)  # type: ignore[arg-type]
        f = plain.forward
        up_perp = u - np.dot(u, f) * f
        roll = 0.0
        if np.linalg.norm(up_perp) > 1e-12 * np.linalg.norm(u):
            roll = math.degrees(math.atan2(np.dot(up_perp, plain.right), np.dot(up_perp, plain.up)))
        return cls(position=tuple(p), yaw=yaw, pitch=pitch, roll=roll, **kw)  # type: ignore[arg-type]

    # --- orientation -------------------------------------------------------------------------

    @cached_property
    def _basis(self) -> np.ndarray:
        """Rows: right, up, forward (world unit vectors)."""
        # float arithmetic, the same operations as numpy's (cross product, scaled sums) and so
        # the same bits, without a dozen small-array calls per pose (it runs once per frame on
        # the caller's thread; tests/streamer/test_camera.py compares it with the numpy form)
        # yaw and roll reduced in degrees first (exactly: fmod; the identity within +-360): a
        # huge angle converted to radians first loses its heading (1e20 deg is 280 deg)
        y, p, r = (math.radians(a) for a in (_turn(self.yaw), self.pitch, _turn(self.roll)))
        sy, cy, sp, cp = math.sin(y), math.cos(y), math.sin(p), math.cos(p)
        f = (sy * cp, cy * cp, sp)
        r0 = (cy, -sy, 0.0)
        u0 = (  # np.cross(r0, f)
            r0[1] * f[2] - r0[2] * f[1],
            r0[2] * f[0] - r0[0] * f[2],
            r0[0] * f[1] - r0[1] * f[0],
        )
        cr, sr = math.cos(r), math.sin(r)
        right = [cr * a - sr * b for a, b in zip(r0, u0, strict=True)]
        up = [cr * b + sr * a for a, b in zip(r0, u0, strict=True)]
        return _readonly(np.array([right, up, list(f)], dtype=np.float64))

    @property
    def forward(self) -> np.ndarray:
        """Unit view direction (world)."""
        return self._basis[2]

    @property
    def right(self) -> np.ndarray:
        """Unit right vector (world); horizontal when roll is 0."""
        return self._basis[0]

    @property
    def up(self) -> np.ndarray:
        """Unit up vector of the image (world); ``right x up = -forward``."""
        return self._basis[1]

    @property
    def heading(self) -> np.ndarray:
        """Unit horizontal view direction ``(x, y)`` from yaw (defined even at pitch +-90)."""
        y = math.radians(_turn(self.yaw))
        return np.array([math.sin(y), math.cos(y)])

    @property
    def eye(self) -> np.ndarray:
        """Position as a float64 array."""
        return np.array(self.position, dtype=np.float64)

    # --- intrinsics --------------------------------------------------------------------------

    @property
    def aspect(self) -> float:
        """Viewport width / height."""
        return self.viewport[0] / self.viewport[1]

    @property
    def tan_half_y(self) -> float:
        """``tan(fov_y / 2)``."""
        return math.tan(math.radians(self.fov_y) / 2.0)

    @property
    def tan_half_x(self) -> float:
        """``tan(fov_x / 2) = aspect * tan(fov_y / 2)`` (square pixels)."""
        return self.aspect * self.tan_half_y

    @property
    def fov_x(self) -> float:
        """Horizontal field of view, degrees."""
        return math.degrees(2.0 * math.atan(self.tan_half_x))

    @property
    def tan_half_diagonal(self) -> float:
        """Tangent of the half diagonal FOV: ``sqrt(tan_half_x**2 + tan_half_y**2)``."""
        return math.hypot(self.tan_half_x, self.tan_half_y)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels: ``(height / 2) / tan(fov_y / 2)`` (Qiu's ``H`` = height)."""
        return (self.viewport[1] / 2.0) / self.tan_half_y

    # --- matrices ----------------------------------------------------------------------------

    def view_matrix(self, absolute: bool = False) -> np.ndarray:
        """4x4 world-to-eye matrix, camera-relative (zero translation) unless ``absolute``.

        Apply the default one to ``p - position`` (float64 on the CPU, then float32 is safe).
        """
        m = np.eye(4)
        m[0, :3] = self.right
        m[1, :3] = self.up
        m[2, :3] = -self.forward
        if absolute:
            m[:3, 3] = -m[:3, :3] @ self.eye
        return m

    def projection_matrix(self) -> np.ndarray:
        """4x4 OpenGL perspective matrix (clip space, NDC z in [-1, 1])."""
        n, f = self.near, self.far
        t = 1.0 / self.tan_half_y
        m = np.zeros((4, 4))
        m[0, 0] = t / self.aspect
        m[1, 1] = t
        m[2, 2] = (f + n) / (n - f)
        m[2, 3] = 2.0 * f * n / (n - f)
        m[3, 2] = -1.0
        return m

    # --- projection --------------------------------------------------------------------------

    def to_camera(self, points_xyz: np.ndarray) -> np.ndarray:
        """``(..., 3)`` camera coordinates ``(right, up, depth)`` of world points (float64)."""
        rel = np.asarray(points_xyz, dtype=np.float64) - self.eye
        return rel @ self._basis.T

    def project(self, points_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact pinhole projection ``(px, py, depth)``; px/py are NaN where depth <= 0."""
        c = self.to_camera(points_xyz)
        depth = c[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(depth > 0.0, self.focal_px / depth, np.nan)
        w, h = self.viewport
        return w / 2.0 + c[..., 0] * s, h / 2.0 - c[..., 1] * s, depth

    def in_view(self, points_xyz: np.ndarray) -> np.ndarray:
        """Boolean: the point is inside the frustum (within the viewport, near <= depth <= far)."""
        px, py, depth = self.project(points_xyz)
        w, h = self.viewport
        with np.errstate(invalid="ignore"):
            return (
                (depth >= self.near)
                & (depth <= self.far)
                & (px >= 0.0)
                & (px <= w)
                & (py >= 0.0)
                & (py <= h)
            )

    def frustum_corners(self, relative: bool = False) -> np.ndarray:
        """``(8, 3)`` corners: near then far plane, each bottom-left, bottom-right, top-right,
        top-left (as seen in the image); world, or relative to the eye if ``relative``."""
        rel = np.array(self.frustum_corners_rel(), dtype=np.float64)
        return rel if relative else rel + self.eye

    def frustum_corners_rel(self) -> list[tuple[float, float, float]]:
        """:meth:`frustum_corners` relative to the eye as Python float triples: each is
        ``d * (forward + sx * right + sy * up)`` for ``d`` near then far (no numpy call per
        corner: ``streamer.frustum.frustum_hull`` runs every frame)."""
        (rx, ry, rz), (ux, uy, uz) = self.right.tolist(), self.up.tolist()
        fx, fy, fz = self.forward.tolist()
        tx, ty = self.tan_half_x, self.tan_half_y
        out = []
        for d in (float(self.near), float(self.far)):
            for sx, sy in ((-tx, -ty), (tx, -ty), (tx, ty), (-tx, ty)):
                out.append(
                    (
                        d * (fx + sx * rx + sy * ux),
                        d * (fy + sx * ry + sy * uy),
                        d * (fz + sx * rz + sy * uz),
                    )
                )
        return out

    def velocity_from(self, prev: Camera, dt: float) -> np.ndarray:
        """World velocity ``(position - prev.position) / dt`` from two successive poses."""
        dt = _finite("dt", dt)
        if not dt > 0.0:
            raise CameraError(f"dt must be > 0 seconds, got {dt}")
        return (self.eye - prev.eye) / dt
