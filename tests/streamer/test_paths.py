"""Fly-through paths: determinism, geometry, keyframe files, the default pass."""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest

from streamer.camera import Camera
from streamer.errors import KeyframeError, PathError, StreamerError
from streamer.frustum import frustum_hull, polygon_meets_rects
from streamer.paths import (
    canyon,
    circle,
    default_flythrough,
    keyframes,
    keyframes_from_records,
    line,
    teleports,
)
from tiler.grid import BlockGrid


def positions(cams: list[Camera]) -> np.ndarray:
    return np.array([c.position for c in cams])


def yaw_diff(a: float, b: float) -> float:
    """Signed shortest difference b - a in degrees."""
    return (b - a + 180.0) % 360.0 - 180.0


# --- line, circle, canyon ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("start", "end", "yaw"),
    [
        ((0, 0, 100), (0, 90, 100), 0.0),
        ((0, 0, 100), (50, 0, 120), 90.0),
        ((10, 10, 100), (0, 0, 100), 225.0),
        ((1e7, 1e7, 5), (1e7 - 30, 1e7, 5), 270.0),
    ],
    ids=["north", "east-climbing", "south-west", "west-far-from-origin"],
)
def test_line(start, end, yaw):
    cams = line(start, end, 11, pitch=-15, fov_y=45)
    assert len(cams) == 11
    p = positions(cams)
    np.testing.assert_allclose(p[0], start)
    np.testing.assert_allclose(p[-1], end)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    np.testing.assert_allclose(steps, steps[0], rtol=1e-6)
    assert all(c.yaw == pytest.approx(yaw) and c.pitch == -15 and c.fov_y == 45 for c in cams)


def test_line_single_frame_and_explicit_yaw():
    cams = line((1, 2, 3), (1, 2, 9), 1, yaw=123.0)
    assert len(cams) == 1
    assert cams[0].position == (1, 2, 3)
    assert cams[0].yaw == 123.0


@pytest.mark.parametrize("look", ["inward", "tangent"])
@pytest.mark.parametrize("clockwise", [True, False])
def test_circle(look, clockwise):
    cams = circle((100, 200), 50, 300, 36, look=look, clockwise=clockwise, pitch=-20)
    p = positions(cams)
    np.testing.assert_allclose(np.hypot(p[:, 0] - 100, p[:, 1] - 200), 50)
    np.testing.assert_allclose(p[:, 2], 300)
    np.testing.assert_allclose(p[0], (100, 250, 300))  # starts north of the centre
    for i, c in enumerate(cams):
        to_centre = np.array([100, 200]) - p[i, :2]
        step = p[(i + 1) % len(p), :2] - p[i - 1, :2]  # central difference ~ tangent
        ref = to_centre if look == "inward" else step
        assert np.dot(c.heading, ref / np.linalg.norm(ref)) == pytest.approx(1.0, abs=2e-2)
    # clockwise seen from above: north -> east
    assert bool(p[1, 0] > 100) is clockwise


def test_circle_rejects_bad_look():
    with pytest.raises(PathError, match="look.*sideways"):
        circle((0, 0), 1, 1, 4, look="sideways")


def test_canyon_follows_terrain():
    def ground(x: float, y: float) -> float:
        return 100.0 + 30.0 * math.sin(x / 50.0) + 0.01 * y

    cams = canyon(ground, (0, 0), (1000, 500), 50, clearance=12.5)
    p = positions(cams)
    np.testing.assert_allclose(p[:, 2], [ground(x, y) + 12.5 for x, y in p[:, :2]])
    np.testing.assert_allclose(p[-1, :2], (1000, 500))
    heading = math.degrees(math.atan2(1000, 500))
    assert all(c.yaw == pytest.approx(heading) for c in cams)


@pytest.mark.parametrize(
    ("fn", "match"),
    [(lambda x, y: float("nan"), "non-finite"), (lambda x, y: "high", "number")],
    ids=["nan", "string"],
)
def test_canyon_rejects_bad_heights(fn, match):
    with pytest.raises(PathError, match=match):
        canyon(fn, (0, 0), (1, 1), 3, clearance=1)


# --- teleports --------------------------------------------------------------------------------

BOUNDS = (1000.0, 2000.0, 50.0, 3000.0, 2500.0, 400.0)


def test_teleports_deterministic_and_in_bounds():
    a = teleports(BOUNDS, 25, seed=42, every=5)
    b = teleports(BOUNDS, 25, seed=42, every=5)
    c = teleports(BOUNDS, 25, seed=43, every=5)
    assert a == b
    assert a != c
    p = positions(a)
    assert (p >= np.array(BOUNDS[:3])).all()
    assert (p <= np.array(BOUNDS[3:])).all()
    assert all(-60 <= cam.pitch <= -10 and 0 <= cam.yaw < 360 for cam in a)
    # held for `every` frames, then a jump
    for i in range(25):
        assert a[i] == a[i - i % 5]
        assert i % 5 == 0 or a[i] == a[i - 1]
    assert len({cam.position for cam in a}) == 5


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"bounds": (0, 0, 0, -1, 1, 1)}, "bounds"),
        ({"bounds": (0, 0, 1, 1)}, "bounds"),
        ({"every": 0}, "every.*0"),
        ({"frames": 0}, "frames.*0"),
        ({"pitch_range": (-10, -60)}, "pitch_range"),
    ],
    ids=["inverted", "four-values", "every", "frames", "pitch-range"],
)
def test_teleports_invalid(kw, match):
    args = {"bounds": BOUNDS, "frames": 10, "seed": 1, "every": 2, **kw}
    with pytest.raises(PathError, match=match) as info:
        teleports(**args)
    assert isinstance(info.value, ValueError)
    assert isinstance(info.value, StreamerError)


# --- keyframes --------------------------------------------------------------------------------

RECORDS = [
    {"t": 0.0, "x": 0.0, "y": 0.0, "z": 100.0, "yaw": 350.0, "pitch": -10.0},
    {"t": 2.0, "x": 20.0, "y": 40.0, "z": 140.0, "yaw": 10.0, "pitch": -30.0},
    {"t": 4.0, "x": 20.0, "y": 0.0, "z": 100.0, "yaw": 200.0, "pitch": -30.0},
]


def _write(tmp_path, fmt: str, records=RECORDS):
    if fmt == "json":
        path = tmp_path / "keys.json"
        path.write_text(json.dumps(records))
    else:
        path = tmp_path / "keys.csv"
        cols = list(records[0])
        lines = [", ".join(cols)] + [",".join(str(r[c]) for c in cols) for r in records]
        path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("fmt", ["json", "csv"])
def test_keyframes_file(tmp_path, fmt):
    cams = keyframes(_write(tmp_path, fmt), 9, fov_y=40)
    assert len(cams) == 9
    np.testing.assert_allclose(cams[0].position, (0, 0, 100))
    np.testing.assert_allclose(cams[-1].position, (20, 0, 100))
    np.testing.assert_allclose(cams[4].position, (20, 40, 140))  # t = 2 exactly
    np.testing.assert_allclose(cams[2].position, (10, 20, 120))  # t = 1
    assert cams[2].pitch == pytest.approx(-20.0)
    assert cams[2].yaw == pytest.approx(0.0, abs=1e-9) or cams[2].yaw == pytest.approx(360.0)
    assert cams[1].yaw == pytest.approx(355.0)  # 350 -> 10 passes north, not south
    # 10 -> 200 is 190 degrees clockwise or 170 anticlockwise: the shorter is anticlockwise
    assert cams[6].yaw == pytest.approx((10.0 - 85.0) % 360.0)
    assert all(c.fov_y == 40 for c in cams)


def test_keyframes_single_and_roll():
    cams = keyframes_from_records([{**RECORDS[0], "roll": 5}], 3)
    assert len(cams) == 3
    assert all(c == cams[0] for c in cams)
    assert cams[0].roll == 5.0


@pytest.mark.parametrize(
    ("records", "match"),
    [
        ([], "at least one"),
        ([{"t": 0, "x": 0, "y": 0, "z": 0, "yaw": 0}], "pitch"),
        ([RECORDS[1], RECORDS[0]], "increase"),
        ([RECORDS[0], {**RECORDS[1], "t": 0.0}], "increase"),
        ([{**RECORDS[0], "z": "high"}], "z.*high"),
        ([{**RECORDS[0], "x": float("inf")}], "x.*finite"),
        ([RECORDS[0], {**RECORDS[1], "pitch": -120}], r"^keyframe 1: pitch must be within"),
    ],
    ids=[
        "empty",
        "missing-column",
        "unsorted",
        "repeated-t",
        "not-a-number",
        "infinite",
        "pitch-beyond-90",
    ],
)
def test_keyframes_invalid(records, match):
    with pytest.raises(KeyframeError, match=match) as info:
        keyframes_from_records(records, 5)
    assert isinstance(info.value, PathError)


def test_keyframes_file_errors(tmp_path):
    bad = tmp_path / "keys.json"
    bad.write_text("{not json")
    with pytest.raises(KeyframeError, match="JSON"):
        keyframes(bad, 3)
    obj = tmp_path / "obj.json"
    obj.write_text(json.dumps({"t": 0}))
    with pytest.raises(KeyframeError, match="list of objects"):
        keyframes(obj, 3)
    other = tmp_path / "keys.txt"
    other.write_text("t,x\n")
    with pytest.raises(KeyframeError, match=r"\.txt"):
        keyframes(other, 3)
    with pytest.raises(FileNotFoundError):
        keyframes(tmp_path / "missing.csv", 3)


def test_a_bad_keyframe_record_names_its_file(tmp_path):
    """A record's fault read from a file starts with the file's path (a user with several
    path files knows which); the records API has no file to name."""
    rows = "t,x,y,z,yaw,pitch\n1,0,0,100,0,-10\n0,0,0,100,0,-10\n"
    f = tmp_path / "flight.csv"
    f.write_text(rows)
    with pytest.raises(KeyframeError, match=r"flight\.csv: keyframe times must strictly"):
        keyframes(f, 3)
    f.write_text("t,x,y,z,yaw,pitch\n0,0,0,100,0,-10\n1,0,0,100,0,95\n")  # 95: beyond 90
    with pytest.raises(KeyframeError, match=r"flight\.csv: keyframe 1 \(line 3\): pitch .* '95'"):
        keyframes(f, 3)


def test_keyframe_files_as_spreadsheets_and_editors_write_them(tmp_path):
    """A "CSV UTF-8" file (a byte-order mark first) was refused as lacking ``t``; a Latin-1
    byte gave a bare UnicodeDecodeError; JSON ``true`` passed as 1.0; a row with more fields
    than the header passed. Controls: the same file without the mark; the record as numbers."""
    rows = "t,x,y,z,yaw,pitch\n0,0,0,100,0,-10\n1,5,0,100,0,-10\n"
    f = tmp_path / "k.csv"
    f.write_bytes(b"\xef\xbb\xbf" + rows.encode())
    bom = keyframes(f, 2)
    f.write_text(rows)
    assert keyframes(f, 2) == bom and bom[1].position[0] == 5.0
    f.write_bytes(rows.replace("100,0,-10\n1", "100,0,-10 \xe9\n1").encode("latin-1"))
    with pytest.raises(KeyframeError, match=r"k\.csv: not UTF-8 text \(byte \d+ is b'\\xe9'\)"):
        keyframes(f, 2)
    f.write_text(rows + "2,5,5,100,0,-10,7\n")
    with pytest.raises(KeyframeError, match=r"k\.csv: line 4 has 7 fields, the header 6"):
        keyframes(f, 2)
    j = tmp_path / "k.json"
    j.write_text(json.dumps([{**RECORDS[0], "x": True}, RECORDS[1]]))
    with pytest.raises(KeyframeError, match=r"keyframe 0: x must be a number, got True"):
        keyframes(j, 2)
    j.write_text(json.dumps([{**RECORDS[0], "x": 1}, RECORDS[1]]))
    assert keyframes(j, 2)[0].position[0] == 1.0
    recs = [{"t": 1, "x": 0, "y": 0, "z": 100, "yaw": 0, "pitch": -10},
            {"t": 0, "x": 0, "y": 0, "z": 100, "yaw": 0, "pitch": -10}]  # fmt: skip
    with pytest.raises(KeyframeError, match="^keyframe times must strictly"):
        keyframes_from_records(recs, 3)


# --- the default fly-through ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("grid", "zmin", "zmax", "fps", "frames"),
    [
        (BlockGrid(height=257, width=257, k=6), 0.0, 30.0, 30.0, 120),
        (BlockGrid(height=4097, width=2049, k=8, dx=30.0, dy=30.0), 200.0, 1800.0, 60.0, 300),
        (BlockGrid(height=65, width=65, k=6, x0=1e7, y0=1e7, dx=2.0, dy=2.0), 5.0, 5.0, 24.0, 200),
        (BlockGrid(height=1025, width=129, k=5, x0=5e5, y0=4e6), -50.0, 400.0, 30.0, 90),
    ],
    ids=["small", "wide-30m", "one-flat-block-far", "tall-narrow-high-relief"],
)
def test_default_flythrough(grid, zmin, zmax, fps, frames):
    cams = default_flythrough(grid, zmin, zmax, frames, fps)
    assert len(cams) == frames
    edge = grid.step * grid.dx
    p = positions(cams)
    # one block edge per second along the path (chords of a smooth curve: slightly shorter)
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    np.testing.assert_allclose(steps, edge / fps, rtol=2e-2)
    assert (p[:, 2] > zmax).all()
    xmin, ymin, xmax, ymax = grid.extent
    assert ((p[:, 0] > xmin) & (p[:, 0] < xmax) & (p[:, 1] > ymin) & (p[:, 1] < ymax)).all()
    # turning: at most twice the mean rate of a loop round the smaller axis (stores 10+ blocks
    # wide turn under ~20 degrees a second; one-block stores are circled fast)
    rate = 2 * 360.0 * edge / (2 * math.pi * 0.3 * min(xmax - xmin, ymax - ymin))
    for a, b in zip(cams, cams[1:], strict=False):
        assert abs(yaw_diff(a.yaw, b.yaw)) < rate / fps
    yaws = [c.yaw for c in cams]
    assert max(abs(yaw_diff(yaws[0], y)) for y in yaws) > 0.0  # it does turn
    for c in cams:
        assert -90.0 < c.pitch <= -20.0
        # the view centre reaches zmin inside the extent and within the far plane:
        # it crosses the terrain there, so every frame sees terrain
        t = (c.position[2] - zmin) / -c.forward[2]
        hit = c.eye + t * c.forward
        assert xmin <= hit[0] <= xmax
        assert ymin <= hit[1] <= ymax
        assert t < c.far
        hull = frustum_hull(c, (zmin, zmax))
        assert polygon_meets_rects(hull, xmin, ymin, xmax, ymax)


def test_default_flythrough_pitch_on_wide_store():
    grid = BlockGrid(height=16385, width=16385, k=10, dx=10.0, dy=10.0)
    cams = default_flythrough(grid, 0.0, 4000.0, 100, 30.0)
    assert all(-30.0 <= c.pitch <= -20.0 for c in cams)
    yaws = [c.yaw for c in cams]
    turn = max(abs(yaw_diff(a, b)) for a, b in zip(yaws, yaws[1:], strict=False))
    assert 0.0 < turn < 1.0  # well under a degree per frame


def test_default_flythrough_speed_and_overrides():
    grid = BlockGrid(height=257, width=257, k=6)
    cams = default_flythrough(grid, 0.0, 10.0, 10, 10.0, speed=5.0, far=777.0, fov_y=50.0)
    steps = np.linalg.norm(np.diff(positions(cams), axis=0), axis=1)
    np.testing.assert_allclose(steps, 0.5, rtol=1e-3)
    assert all(c.far == 777.0 and c.fov_y == 50.0 for c in cams)
    assert default_flythrough(grid, 0.0, 10.0, 3, 10.0) == default_flythrough(
        grid, 0.0, 10.0, 3, 10.0
    )


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"zmin": 5.0, "zmax": 1.0}, "zmin"),
        ({"fps": 0.0}, "fps"),
        ({"speed": -1.0}, "speed.*-1.0"),
        ({"frames": 0}, "frames"),
    ],
    ids=["z-inverted", "fps", "speed", "frames"],
)
def test_default_flythrough_invalid(kw, match):
    args = {
        "grid": BlockGrid(height=65, width=65, k=6),
        "zmin": 0.0,
        "zmax": 1.0,
        "frames": 5,
        "fps": 30.0,
        **kw,
    }
    with pytest.raises(PathError, match=match):
        default_flythrough(**args)


def test_default_flythrough_refuses_a_speed_beyond_a_loop_per_frame():
    """`stream --speed 1e25` ended with "yaw must be finite, got nan"; now the speed is refused
    naming the bound, and a speed at the bound still gives finite poses."""
    grid = BlockGrid(height=65, width=65, k=6)
    with pytest.raises(PathError, match=r"speed 1e\+25 at 30 fps .* more than the default"):
        default_flythrough(grid, 0.0, 1.0, 5, 30.0, speed=1e25)
    bound = float(
        re.search(r"at most (\S+) ", _message(grid, 1e9)).group(1)  # type: ignore[union-attr]
    )
    cams = default_flythrough(grid, 0.0, 1.0, 5, 30.0, speed=0.999 * bound)
    assert all(np.isfinite([c.yaw, c.pitch, *c.position]).all() for c in cams)


def _message(grid, speed) -> str:
    try:
        default_flythrough(grid, 0.0, 1.0, 5, 30.0, speed=speed)
    except PathError as exc:
        return str(exc)
    raise AssertionError("not refused")
