"""The interactive viewer (``terrastream view``): a GLFW window, fly controls, live tau.

Each frame: poll the keys and the mouse, move the camera (:func:`fly`, pure), let the streaming
session schedule loads for it (``workers`` loader threads, frustum-hull culling, as
:mod:`render.pipeline` does), upload what arrived, select at the current tau, draw with
:class:`render.renderer.TerrainRenderer` into its offscreen framebuffer, blit that to the window
and lay the status line (drawn with Pillow into a texture, refreshed 4 times a second) over it.

GLFW (the ``glfw`` wheel bundles libglfw) creates an OpenGL 4.5 core context through GLX on X11;
moderngl attaches to it. ``frames``/``screenshot`` run a fixed number of frames without input and
save the last one (the tests do this under Xvfb).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import moderngl
import numpy as np

from render.errors import RenderError
from render.ground_watch import GroundWatch
from render.pipeline import ViewOptions, session_patch_log2
from render.renderer import RenderConfig, RenderStats, TerrainRenderer
from render.step import frame_step
from render.strategies import warm_up_kernels
from render.strategies.base import DrawOptions
from render.views import near_plane
from streamer.camera import Camera
from streamer.gcfreeze import freeze_heap
from streamer.run import close_for_verdict, flight_problem
from streamer.session import LoadError, open_session
from tiler.store import TerrainStore

log = logging.getLogger(__name__)
TAU_STEP = math.sqrt(2.0)  # +/- multiply / divide tau by this
BOOST = 5.0  # Shift
LOOK_DEG_PER_PX = 0.15


class ViewerUnavailableError(RenderError, RuntimeError):
    """No window could be opened (no display, no glfw, no OpenGL 4.5 through GLX)."""


# --- controls (pure) ------------------------------------------------------------------------


@dataclass(frozen=True)
class Pose:
    """Camera position (world units) and orientation (degrees; yaw clockwise from north)."""

    x: float
    y: float
    z: float
    yaw: float
    pitch: float

    @classmethod
    def of(cls, camera: Camera) -> Pose:
        """The pose of ``camera`` (its position, yaw and pitch)."""
        return cls(*camera.position, camera.yaw, camera.pitch)


@dataclass(frozen=True)
class Controls:
    """One frame's input: axes in -1..1 (W/S, D/A, E or Space / Q or C), mouse motion in px."""

    forward: float = 0.0
    right: float = 0.0
    up: float = 0.0
    fast: bool = False
    look_dx: float = 0.0  # mouse right = turn right
    look_dy: float = 0.0  # mouse down (screen y grows downwards) = look down


def fly(
    pose: Pose, c: Controls, dt: float, speed: float, deg_per_px: float = LOOK_DEG_PER_PX
) -> Pose:
    """The pose after ``dt`` seconds: turn by the mouse (pitch kept in [-89, 89]), then move
    along the view direction (W/S), the horizontal right (D/A) and world up (E/Q) at ``speed``
    units/s (times :data:`BOOST` with Shift); diagonal moves are not faster."""
    yaw = (pose.yaw + c.look_dx * deg_per_px) % 360.0
    pitch = min(89.0, max(-89.0, pose.pitch - c.look_dy * deg_per_px))
    y, p = math.radians(yaw), math.radians(pitch)
    f = np.array([math.sin(y) * math.cos(p), math.cos(y) * math.cos(p), math.sin(p)])
    r = np.array([math.cos(y), -math.sin(y), 0.0])
    move = c.forward * f + c.right * r + np.array([0.0, 0.0, c.up])
    n = float(np.linalg.norm(move))
    if n > 1.0:
        move /= n
    step = move * speed * (BOOST if c.fast else 1.0) * dt
    return Pose(pose.x + step[0], pose.y + step[1], pose.z + step[2], yaw, pitch)


def speed_for(z: float, zlo: float, spacing: float) -> float:
    """Flying speed (units/s): half the height above the lowest terrain, at least 10 samples."""
    return max(10.0 * spacing, 0.5 * (z - zlo))


def camera_at(pose: Pose, store: TerrainStore, size: tuple[int, int], fov: float = 45.0) -> Camera:
    """The camera of a pose, with near/far fitted to its height and the DEM's extent."""
    x0, y0, x1, y1 = store.grid.extent
    zlo, zhi = float(np.nanmin(store.index.zmin)), float(np.nanmax(store.index.zmax))
    h = max(abs(pose.z - zlo), abs(pose.z - zhi), 1.0)
    reach = math.hypot(x1 - x0, y1 - y0) + math.hypot(
        pose.x - 0.5 * (x0 + x1), pose.y - 0.5 * (y0 + y1)
    )
    tan_diag = math.tan(math.radians(fov) / 2) * math.hypot(1.0, size[0] / size[1])
    cap = max(0.5, 1e-3 * abs(pose.z - zlo))
    near = near_plane(store, (pose.x, pose.y, pose.z), tan_diag, cap)  # follows the clearance
    return Camera(
        (pose.x, pose.y, pose.z),
        yaw=pose.yaw,
        pitch=pose.pitch,
        fov_y=fov,
        viewport=size,
        near=near,
        far=max(reach + h, 10 * near) * 1.2,
    )


# --- window, overlay --------------------------------------------------------------------------

_QUAD_VS = """#version 330
in vec2 in_pos;
out vec2 uv;
uniform vec4 rect;  // x0, y0, x1, y1 in NDC
void main() {
    uv = vec2(in_pos.x, 1.0 - in_pos.y);
    gl_Position = vec4(mix(rect.xy, rect.zw, in_pos), 0.0, 1.0);
}"""
_QUAD_FS = """#version 330
in vec2 uv;
out vec4 colour;
uniform sampler2D tex;
void main() { colour = texture(tex, uv); }"""


class _Overlay:
    """One line of text at the top left: Pillow draws it into an RGBA texture."""

    def __init__(self, ctx: moderngl.Context, size: tuple[int, int]) -> None:
        from PIL import ImageFont

        self.ctx, self.size = ctx, size
        try:
            self.font = ImageFont.load_default(size=15)
        except TypeError:  # Pillow < 10.1: the bitmap font
            self.font = ImageFont.load_default()
        self.prog = ctx.program(vertex_shader=_QUAD_VS, fragment_shader=_QUAD_FS)
        quad = np.array([0, 0, 1, 0, 0, 1, 1, 1], dtype="f4")
        self.vbo = ctx.buffer(quad.tobytes())
        self.vao = ctx.vertex_array(self.prog, [(self.vbo, "2f", "in_pos")])
        self.tex: moderngl.Texture | None = None
        self.text = None

    def set(self, text: str) -> None:
        if text == self.text:
            return
        from PIL import Image, ImageDraw

        self.text = text
        box = ImageDraw.Draw(Image.new("RGBA", (1, 1))).textbbox((0, 0), text, font=self.font)
        w = min(self.size[0], box[2] + 12)
        h = min(self.size[1], box[3] + 8)
        img = Image.new("RGBA", (w, h), (0, 0, 0, 150))
        ImageDraw.Draw(img).text((6, 3), text, font=self.font, fill=(255, 255, 255, 255))
        if self.tex is not None:
            self.tex.release()
        self.tex = self.ctx.texture((w, h), 4, img.tobytes())
        W, H = self.size
        self.prog["rect"].value = (-1.0, 1.0 - 2.0 * h / H, -1.0 + 2.0 * w / W, 1.0)

    def draw(self) -> None:
        if self.tex is None:
            return
        self.ctx.disable(moderngl.DEPTH_TEST)
        self.ctx.enable(moderngl.BLEND)
        self.ctx.blend_func = moderngl.SRC_ALPHA, moderngl.ONE_MINUS_SRC_ALPHA
        self.tex.use(0)
        self.prog["tex"].value = 0
        self.vao.render(moderngl.TRIANGLE_STRIP)
        self.ctx.disable(moderngl.BLEND)


def open_window(
    size: tuple[int, int], title: str, *, visible: bool = True
) -> tuple[Any, Any, moderngl.Context]:
    """``(glfw, window, ctx)``: a fixed-size window with a current OpenGL 4.5 core context."""
    try:
        import glfw
    except Exception as exc:  # noqa: BLE001 - ImportError, or libglfw failing to load
        raise ViewerUnavailableError(
            f"the viewer needs the glfw package (pip install glfw, which bundles libglfw): {exc}"
        ) from exc
    glfw.ERROR_REPORTING = "raise"  # GLFW's own message, e.g. "X11: DISPLAY is missing"
    try:
        if not glfw.init():
            raise glfw.GLFWError("glfwInit failed")
        for hint, value in (
            (glfw.CONTEXT_VERSION_MAJOR, 4),
            (glfw.CONTEXT_VERSION_MINOR, 5),
            (glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE),
            (glfw.OPENGL_FORWARD_COMPAT, True),
            (glfw.RESIZABLE, False),
            (glfw.VISIBLE, visible),
        ):
            glfw.window_hint(hint, value)
        win = glfw.create_window(size[0], size[1], title, None, None)
        glfw.make_context_current(win)
    except glfw.GLFWError as exc:
        glfw.terminate()
        has_display = bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))
        why = (
            "the display has no OpenGL 4.5 core profile: check `glxinfo -B` (a driver or "
            "MESA_GL_VERSION_OVERRIDE below 4.5?)"
            if has_display
            else "needs a display: on a headless machine run it inside xvfb-run"
        )
        raise ViewerUnavailableError(f"cannot open an OpenGL 4.5 window: {exc} ({why})") from exc
    finally:
        glfw.ERROR_REPORTING = "warn"
    for backend in (None, "egl"):  # GLX on X11; EGL when GLFW made an EGL context (Wayland)
        try:
            ctx = moderngl.create_context(require=450, **({"backend": backend} if backend else {}))
            return glfw, win, ctx
        except Exception as exc:  # noqa: BLE001 - any driver failure means "no viewer here"
            err = exc
    glfw.terminate()
    raise ViewerUnavailableError(f"cannot use the window's OpenGL context: {err}")


# --- the loop ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class ViewResult:
    """What a (scripted) viewer run did."""

    frames: int
    last: RenderStats | None
    tau: float
    resident_mb: float
    screenshot: Path | None
    # why a scripted run's view is incomplete (streamer.run.flight_problem: blocks that could
    # not be read, reads never answered), its screenshot then removed; None: it is whole
    # (a scripted run whose last frame drew no terrain pixel, last.drawn_px == 0, has its
    # screenshot removed too: a picture of sky is not a view of the store)
    problem: str | None = None
    # where the last frame's camera (the screenshot's) was against the ground: "" when clear
    # of it, else render.views.clearance_note's clause (below the terrain, near plane clips it)
    ground: str = ""
    # blocks of the DEM the last frame's camera saw (0: none, it looked away; None: no frame)
    visible_blocks: int | None = None


def status_line(
    fps: float, st: RenderStats, tau: float, metric: str, mb: float, wire: bool,
    build_ms: float = 0.0,
) -> str:  # fmt: skip
    """The on-screen line (also the window title); ``build_ms``: the frame's per-block builds
    on the render thread (shown when at least 0.05 ms)."""
    build = f" + build {build_ms:.1f} ms" if build_ms >= 0.05 else ""
    return (
        f"{fps:5.1f} fps | {st.triangles:,} triangles | tau {tau:.3g} px ({metric}) | "
        f"resident {mb:.1f} MB | sel {st.selection_ms:.1f} ms{build}"
        + (" | wireframe" if wire else "")
    )


def run_viewer(
    store: TerrainStore,
    start: Camera,
    *,
    tau: float = 1.0,
    metric: str = "qiu",
    patch_log2: int = 4,
    workers: int = 4,
    budget_mb: float = 512.0,
    wireframe: bool = False,
    frames: int | None = None,
    screenshot: str | Path | None = None,
    lod: str = "qiu",
    options: ViewOptions | None = None,
) -> ViewResult:
    """Open the window and fly until it closes (or for ``frames`` frames, without input);
    ``lod`` names the LOD strategy (:mod:`render.strategies`); ``options``, when given,
    replaces ``lod``, ``tau``, ``metric``, ``patch_log2`` and ``wireframe`` (the start)."""
    o = options or ViewOptions(lod, tau, metric, patch_log2, wireframe)
    size = tuple(start.viewport)
    glfw, win, ctx = open_window(size, f"terrastream view {store.url}", visible=True)
    try:
        return _loop(glfw, win, ctx, store, start, o, workers, budget_mb, frames, screenshot)
    finally:
        glfw.terminate()


def _loop(glfw, win, ctx, store, start, o: ViewOptions, workers, budget_mb, frames,
          screenshot) -> ViewResult:  # fmt: skip
    from render.strategies import get_strategy, stream_metric

    lod, metric = o.lod, o.metric
    size, scripted = tuple(start.viewport), frames is not None
    fb = glfw.get_framebuffer_size(win)
    size = (int(fb[0]), int(fb[1])) if fb[0] > 0 else size
    r = TerrainRenderer(store, RenderConfig(size=size, patch_log2=o.patch_log2), ctx=ctx)
    strat = get_strategy(lod, r, **o.strategy_options())
    strat.build_in_background()  # a level change's texture off the render thread
    overlay = _Overlay(ctx, size)
    zlo = float(np.nanmin(store.index.zmin))
    pose, fov = Pose.of(start), start.fov_y
    watch = GroundWatch(store, background=True)  # a warning once per descent below ground
    state = {"tau": float(o.tau), "wire": o.wireframe, "quit": False, "captured": False}

    def capture(on: bool) -> None:  # mouse look with a hidden, captured cursor
        state["captured"], state["fresh"] = on, True  # fresh: skip the jump on (un)capture
        glfw.set_input_mode(win, glfw.CURSOR, glfw.CURSOR_DISABLED if on else glfw.CURSOR_NORMAL)

    glfw.swap_interval(0 if scripted else 1)

    def on_key(_w, key, _sc, action, mods) -> None:
        if action != glfw.PRESS:
            return
        if key in (glfw.KEY_EQUAL, glfw.KEY_KP_ADD):
            state["tau"] *= TAU_STEP
        elif key in (glfw.KEY_MINUS, glfw.KEY_KP_SUBTRACT):
            state["tau"] = max(state["tau"] / TAU_STEP, 1.0 / 64)
        elif key in (glfw.KEY_F, glfw.KEY_TAB):
            state["wire"] = not state["wire"]
        elif key == glfw.KEY_ESCAPE:
            state["quit"] = not state["captured"]
            capture(False)

    def on_click(_w, button, action, _mods) -> None:
        if action == glfw.PRESS and not scripted:
            capture(True)

    glfw.set_key_callback(win, on_key)
    glfw.set_mouse_button_callback(win, on_click)
    capture(not scripted)
    held = lambda *keys: any(glfw.get_key(win, k) == glfw.PRESS for k in keys)  # noqa: E731
    mouse = glfw.get_cursor_pos(win)
    n, frame_s, last, shot, mb, tick = 0, 0.0, None, None, 0.0, 0.0
    frozen = False  # the collector's heap frozen once the kernels have loaded
    try:
        session = open_session(
            store,
            budget_mb=budget_mb,
            workers=workers,
            tau=state["tau"],
            metric=stream_metric(lod, metric),
            patch_log2=session_patch_log2(strat, r),  # (chunk-tessellation: its chunks)
            culling="hull",
            nodata=o.nodata,
        )
    except BaseException:
        strat.close()
        r.close()
        raise
    # the strategies' compiled kernels, loaded beside the first frames (which use numpy's)
    warm = threading.Thread(
        target=warm_up_kernels, kwargs=strat.warm_up_args(), name="terrastream-warm-kernels"
    )
    warm.start()
    t_prev = time.perf_counter()
    try:
        while not glfw.window_should_close(win) and not state["quit"]:
            if scripted and n >= frames:
                break
            glfw.poll_events()
            now = time.perf_counter()
            dt, t_prev = (min(now - t_prev, 0.25) if n else 0.0), now
            if n > 1:  # smoothed frame time (frame 0 waited for its data)
                frame_s = dt if frame_s == 0.0 else 0.8 * frame_s + 0.2 * dt
            pos = glfw.get_cursor_pos(win)
            moved = state["captured"] and not state.pop("fresh", False)
            look = (pos[0] - mouse[0], pos[1] - mouse[1]) if moved else (0.0, 0.0)
            mouse = pos
            axis = lambda plus, minus: float(held(*plus)) - float(held(*minus))  # noqa: E731
            c = Controls(
                forward=axis((glfw.KEY_W, glfw.KEY_UP), (glfw.KEY_S, glfw.KEY_DOWN)),
                right=axis((glfw.KEY_D, glfw.KEY_RIGHT), (glfw.KEY_A, glfw.KEY_LEFT)),
                up=axis((glfw.KEY_E, glfw.KEY_SPACE), (glfw.KEY_Q, glfw.KEY_C)),
                fast=held(glfw.KEY_LEFT_SHIFT, glfw.KEY_RIGHT_SHIFT),
                look_dx=look[0],
                look_dy=look[1],
            )
            pose = fly(pose, c, dt, speed_for(pose.z, zlo, store.grid.dx))
            cam = camera_at(pose, store, size, fov)
            last_frame = scripted and n == frames - 1
            # (the start camera: make_camera warned; the last one's is the screenshot's; both
            # frames wait for their data anyway)
            watch.check(cam, quiet=n == 0, wait=n == 0 or last_frame)
            if session.config.tau != state["tau"]:  # live tau: the session loads for it too
                session.set_tau(state["tau"])
            try:
                step = frame_step(
                    session, strat, cam, state["tau"], metric, dt=dt if n else None,
                    wait=n == 0 or last_frame,
                    options=DrawOptions(wireframe=state["wire"], lod_colour=o.lod_colour),
                )  # fmt: skip
            except LoadError as exc:  # reported once; the session keeps going without it
                log.warning("%s", exc)
                continue
            frame, last = step.frame, step.stats
            if last_frame:  # a scripted run's view: terrain pixels drawn (0: sky, or nothing)
                last = replace(last, drawn_px=r.drawn_pixels() if last.triangles else 0)
            ctx.copy_framebuffer(ctx.screen, r.fbo)
            ctx.screen.use()
            fps = 1.0 / frame_s if frame_s > 0.0 else 0.0
            mb = frame.stats.resident_bytes / 2**20
            if now - tick > 0.25 or last_frame:
                tick = now
                label = metric if strat.uses_metric else strat.name  # whose error tau bounds
                text = (
                    status_line(fps, last, state["tau"], label, mb, state["wire"], strat.build_ms)
                    + watch.status()
                )
                overlay.set(text)
                glfw.set_window_title(win, f"terrastream view | {text}")
            overlay.draw()
            if last_frame and screenshot is not None:
                shot = Path(screenshot)
                _save(ctx, size, shot)
            glfw.swap_buffers(win)
            n += 1
            if not frozen and not warm.is_alive():  # start-up done: see streamer.gcfreeze
                freeze_heap()
                frozen = True
    finally:
        # (reads in flight may finish, fail or never answer: a scripted run says which)
        unfinished, summary = close_for_verdict(session)
        warm.join(timeout=30.0)  # an import is not interruptible; it ends within seconds
        watch.close()
        try:
            strat.close()
        finally:
            r.close()
    problem = flight_problem(summary, unfinished, store.url) if scripted else None
    blank = last is not None and last.drawn_px == 0  # no terrain pixel: not a view of it
    if (problem or blank) and shot is not None:  # drawn without its data, or of no terrain
        shot.unlink(missing_ok=True)
        shot = None
    seen = None if last is None else frame.stats.visible_blocks
    return ViewResult(n, last, state["tau"], mb, shot, problem, watch.note, seen)


def _save(ctx: moderngl.Context, size: tuple[int, int], path: Path) -> None:
    """Write the window's back buffer (terrain + status line) as an image (the format from
    the extension: :func:`render.flythrough.encode_image`), whole or not at all."""
    from render.flythrough import encode_image
    from tiler.atomic import write_atomic

    data = ctx.screen.read(viewport=(0, 0, *size), components=3, alignment=1)
    img = np.frombuffer(data, np.uint8).reshape(size[1], size[0], 3)[::-1]
    write_atomic(os.path.abspath(path), encode_image(img, path))
