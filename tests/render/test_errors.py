"""Library errors of the renderer carry values and advice but no CLI flag names; a front end
puts its own names in (:meth:`render.errors.CameraSpecError.message`)."""

from __future__ import annotations

import numpy as np
import pytest

from render.errors import CameraSpecError
from render.views import make_camera, parse_triple

FLAGS = {"position": "--camera", "look_at": "--look-at", "yaw": "--yaw", "pitch": "--pitch"}


class _Store:
    """The least of a store ``make_camera`` reads (extent, spacing, z range)."""

    class grid:  # noqa: N801 - mimics TerrainStore.grid
        extent = (0.0, 0.0, 1000.0, 1000.0)
        x0, y0 = 0.0, 1000.0  # the top-left corner
        dx = dy = 10.0

    class index:  # noqa: N801
        zmin = np.array([[0.0]])
        zmax = np.array([[100.0]])


@pytest.mark.parametrize(
    ("kw", "library", "cli"),
    [
        ({"position": "1,2"}, "position must be three numbers x,y,z, got '1,2'",
         "--camera must be three numbers"),
        ({"look_at": "1,2,3"}, "look_at/yaw/pitch need position x,y,z",
         "--look-at/--yaw/--pitch need --camera x,y,z"),
        ({"position": "1,2,300", "look_at": "5,5,5", "yaw": 3.0},
         "give either look_at or yaw/pitch, not both", "give either --look-at or --yaw/--pitch"),
        ({"position": "1,2,300", "look_at": "5,x,5"}, "look_at must be three numbers",
         "--look-at must be three numbers"),
    ],
)  # fmt: skip
def test_camera_errors_name_parameters_not_flags(kw, library, cli):
    with pytest.raises(CameraSpecError) as info:
        make_camera(_Store(), (64, 48), **kw)
    exc = info.value
    assert library in str(exc) and "--" not in str(exc)
    assert cli in exc.message(FLAGS)
    assert exc.params and set(exc.params) <= set(FLAGS)


def test_parse_triple_reports_the_value():
    assert parse_triple("1,2,3", "position") == (1.0, 2.0, 3.0)
    with pytest.raises(CameraSpecError, match=r"position must be three numbers x,y,z, got 'a'"):
        parse_triple("a", "position")


def test_wrapped_camera_errors_keep_their_text():
    exc = CameraSpecError("{detail}", detail="near {plane} must be > 0")
    assert str(exc) == "near {plane} must be > 0" and exc.params == ()
