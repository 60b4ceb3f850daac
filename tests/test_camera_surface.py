"""Attitude conventions against hand-worked cases; projection and ray casting round trips."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rasterio.transform import from_origin

from geoortho.core.camera import (
    Intrinsics,
    Pose,
    pixel_rays,
    project_points,
    rotation_from_ypr,
    ypr_from_rotation,
)
from geoortho.core.surface import FlatSurface, GridSurface

# Camera axes: x = image right, y = image down, z = optical axis.
RIGHT, DOWN, AXIS = np.eye(3)
s30, c30 = 0.5, np.sqrt(3) / 2


@pytest.mark.parametrize(
    "ypr, axis, right, image_down",
    [
        # nadir, image top to the north: right = east, image-down = south
        ((0, -90, 0), (0, 0, -1), (1, 0, 0), (0, -1, 0)),
        # nadir, yaw 90 (nose east): image top east, right = south, image-down = west
        ((90, -90, 0), (0, 0, -1), (0, -1, 0), (-1, 0, 0)),
        # horizon, looking north: axis north, right east, image-down is down
        ((0, 0, 0), (0, 1, 0), (1, 0, 0), (0, 0, -1)),
        # horizon, looking west (yaw -90): right = north
        ((-90, 0, 0), (-1, 0, 0), (0, 1, 0), (0, 0, -1)),
        # looking north 30° down: axis tilts down by 30°
        ((0, -30, 0), (0, c30, -s30), (1, 0, 0), (0, -s30, -c30)),
        # horizon north, roll 30° right side down: the right edge dips
        ((0, 0, 30), (0, 1, 0), (c30, 0, -s30), (-s30, 0, -c30)),
    ],
)
def test_rotation_hand_worked(ypr, axis, right, image_down):
    r = rotation_from_ypr(*ypr)
    assert np.allclose(r @ AXIS, axis, atol=1e-12)
    assert np.allclose(r @ RIGHT, right, atol=1e-12)
    assert np.allclose(r @ DOWN, image_down, atol=1e-12)
    assert np.allclose(r.T @ r, np.eye(3)) and np.linalg.det(r) == pytest.approx(1.0)


@settings(max_examples=200, deadline=None)
@given(st.floats(-179.9, 179.9), st.floats(-89.5, 89.5), st.floats(-60, 60))
def test_ypr_round_trip(yaw, pitch, roll):
    assert np.allclose(ypr_from_rotation(rotation_from_ypr(yaw, pitch, roll)), (yaw, pitch, roll), atol=1e-7)


def test_rotation_vectorised_matches_scalar():
    y, p, r = np.array([10.0, -100.0]), np.array([-80.0, -45.0]), np.array([1.0, -3.0])
    many = rotation_from_ypr(y, p, r)
    assert many.shape == (2, 3, 3)
    assert np.allclose(many[1], rotation_from_ypr(-100.0, -45.0, -3.0))


def test_pixel_convention_centre_of_top_left_pixel():
    intr = Intrinsics(4, 2, 10.0)
    assert (intr.cx_px, intr.cy_px) == (1.5, 0.5)
    pose = Pose.from_ypr((0, 0, 10), 0, -90, 0)
    # The ray through the principal point goes straight down.
    assert np.allclose(pixel_rays(np.array([[1.5, 0.5]]), intr, pose), [[0, 0, -1]])


@pytest.mark.parametrize("distortion", [(), (-0.05, 0.02, 0.001, -0.0005, 0.0)])
def test_project_and_cast_round_trip(distortion):
    intr = Intrinsics(1600, 1067, 1100.0, distortion=distortion)
    pose = Pose.from_ypr((100.0, 200.0, 60.0), 33.0, -70.0, 2.0)
    ground = FlatSurface(5.0)
    px = np.random.default_rng(0).uniform([0, 0], [1599, 1066], (200, 2))
    hits = ground.intersect(pose.center, pixel_rays(px, intr, pose))
    assert hits.hit.all()
    back, depth = project_points(hits.points, intr, pose)
    assert (depth > 0).all()
    assert np.abs(back - px).max() < 1e-6


def test_points_behind_camera_are_nan():
    intr = Intrinsics(100, 100, 50.0)
    pose = Pose.from_ypr((0, 0, 10), 0, -90, 0)
    px, depth = project_points(np.array([[0, 0, 20.0], [0, 0, 0.0]]), intr, pose)
    assert np.isnan(px[0]).all() and depth[0] < 0 and np.allclose(px[1], [49.5, 49.5])


def _box_surface() -> GridSurface:
    """Flat ground at 0 m with a 10 m high, 4 m wide box around x in [48, 52] m, 0.5 m cells."""
    grid = np.zeros((200, 200), np.float32)
    grid[:, 96:104] = 10.0
    return GridSurface(grid, from_origin(0.0, 100.0, 0.5, 0.5))


def test_grid_intersect_hits_the_roof_and_the_wall():
    surf = _box_surface()
    # straight down onto the roof
    h = surf.intersect(np.array([50.0, 50.0, 100.0]), np.array([[0.0, 0.0, -1.0]]))
    assert h.hit.all() and h.points[0, 2] == pytest.approx(10.0, abs=1e-3)
    # oblique from the west: meets the wall x = 48 at height between 0 and 10
    d = np.array([[1.0, 0.0, -0.5]]) / np.sqrt(1.25)
    h = surf.intersect(np.array([20.0, 50.0, 18.0]), d)
    # ray z at x=48 is 18 - 0.5*28 = 4 m: it hits the wall, not the ground beyond
    assert h.hit.all()
    assert h.points[0, 0] == pytest.approx(48.0, abs=0.3)
    # a ray that passes over the box lands on the ground beyond it
    h = surf.intersect(np.array([10.0, 50.0, 40.0]), d)
    assert h.points[0, 0] == pytest.approx(90.0, abs=0.3) and h.points[0, 2] == pytest.approx(0.0, abs=1e-3)


def test_grid_intersect_misses_outside_and_reports_it():
    surf = _box_surface()
    h = surf.intersect(np.array([50.0, 50.0, 100.0]), np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]))
    assert h.hit.tolist() == [False, True]


@pytest.mark.parametrize("extend", [False, True])
def test_grid_intersect_compiled_is_the_plain_march(monkeypatch, extend):
    """A photo's worth of rays (over COMPILED_MIN_RAYS) is marched a ray at a time in a compiled loop:
    the same landings as the numpy march, bit for bit, over roofs, walls, a pit, holes and the grid's
    edge (a synthetic survey rendered either way is the same survey)."""
    from geoortho.core import kernels, surface

    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:400, 0:400]
    grid = (0.02 * xx + 1.5 * np.sin(yy / 30.0)).astype(np.float32)
    for _ in range(25):  # blocks, some tall, and a pit
        r, c, h, w = rng.integers(10, 380), rng.integers(10, 380), rng.integers(5, 30), rng.integers(5, 30)
        grid[r : r + h, c : c + w] += rng.uniform(-4.0, 12.0)
    grid[200:220, 50:80] = np.nan  # no data: rays pass
    surf = GridSurface(grid, from_origin(1000.0, 5000.0, 0.25, 0.25), extend=extend)
    n = 300_000
    origins = np.c_[rng.uniform(990, 1110, n), rng.uniform(4890, 5010, n), rng.uniform(40, 90, n)]
    dirs = np.c_[rng.normal(0, 0.5, n), rng.normal(0, 0.5, n), -np.ones(n)]
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    runs = {}
    for floor in (10**12, 1):  # numpy, then compiled
        monkeypatch.setattr(surface, "COMPILED_MIN_RAYS", floor)
        runs[floor] = surf.intersect(origins, dirs, max_range_m=500.0, step_m=0.3)
    a, b = runs[10**12], runs[1]
    assert kernels.compiled(surface._march_each) is not None  # numba is here: both paths were taken
    off_grid = a.extended if extend else ~a.hit  # rays that leave the grid or cross the hole
    assert off_grid is not None and 0.0 < off_grid.mean() < 0.7
    assert np.array_equal(a.hit, b.hit) and np.array_equal(a.range_m, b.range_m)
    assert np.array_equal(a.points, b.points)


def test_grid_surface_rejects_rotated_grids():
    with pytest.raises(ValueError, match="north-up"):
        GridSurface(np.zeros((2, 2)), from_origin(0, 0, 1, -1))


def test_mapped_surface_travels_as_its_file_name(tmp_path):
    """A surface sent to pool workers: mapped from one file, its pickle is its name and caches (not the
    grid), it rays and heights as the original, and a worker writing into it leaves the file alone."""
    import pickle

    surf = _box_surface()
    grid = surf.grid.copy()
    grid[:5, :5] = np.nan
    surf = GridSurface(grid, surf.transform, extend=True)
    mapped = surf.mapped(tmp_path)
    sent = pickle.dumps(mapped)
    assert len(sent) + 0.9 * grid.nbytes < len(pickle.dumps(surf))  # the same caches, less the grid
    got = pickle.loads(sent)
    assert (got.z_min, got.z_max, got.extend) == (0.0, 10.0, True)
    assert np.array_equal(got.grid, grid, equal_nan=True)
    x, y = np.array([1.0, 50.0, 99.0, 150.0]), np.array([99.0, 50.0, 1.0, 50.0])  # one beyond the grid
    assert np.array_equal(got.elevation(x, y), surf.elevation(x, y))
    o, d = np.array([20.0, 50.0, 18.0]), np.array([[1.0, 0.0, -0.5]]) / np.sqrt(1.25)
    assert np.allclose(got.intersect(o, d).points, surf.intersect(o, d).points)
    got.grid[50, 50] = 99.0  # copy-on-write: the worker's own page
    assert pickle.loads(sent).grid[50, 50] == grid[50, 50]
    # the grid without data is refused whether or not it is all NaN from the start
    with pytest.raises(ValueError, match="no data"):
        GridSurface(np.full((3, 3), np.nan), surf.transform)
    with pytest.raises(ValueError, match="no data"):
        GridSurface(np.zeros((0, 3)), surf.transform)
