"""copc: a cloud rewritten as a Cloud-Optimized Point Cloud keeps every point, and its octree is
one a reader can walk (laspy's COPC reader here; QGIS's own in tests_qgis)."""

from __future__ import annotations

import struct

import laspy
import numpy as np
import pytest
from pyproj import CRS

import geoortho
from geoortho.core import copc as core_copc
from geoortho.core.pointcloud import write_las
from geoortho.errors import InputError

UTM = CRS("EPSG:32629")


def _cloud(path, n=60_000, seed=0, crs=UTM):
    """A terrain with a block on it, coloured and classed, over 200 x 150 m."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 200, n) + 483_000
    y = rng.uniform(0, 150, n) + 4_288_000
    z = 100 + 0.05 * (x - 483_000) + np.where((np.abs(x - 483_100) < 15) & (np.abs(y - 4_288_075) < 10), 8.0, 0.0)
    rgb = rng.uniform(0, 1, (n, 3))
    cls = np.where(z - 100 - 0.05 * (x - 483_000) > 1, 6, 2).astype(np.uint8)
    write_las(path, np.c_[x, y, z], crs, rgb=rgb, classification=cls)
    return path


def _rows(las):
    return np.sort(
        np.rec.fromarrays([las.X, las.Y, las.Z, las.red, las.green, las.classification], names="x,y,z,r,g,c"),
        order=["x", "y", "z", "r", "g", "c"],
    )


@pytest.mark.parametrize("subtree_points", [10_000_000, 8_000])  # in memory; split into subtrees on disk
def test_every_point_is_written_once_and_the_octree_can_be_walked(tmp_path, monkeypatch, subtree_points):
    monkeypatch.setattr(core_copc, "SUBTREE_POINTS", subtree_points)
    monkeypatch.setattr(core_copc, "LEAF_POINTS", 3_000)
    source = _cloud(tmp_path / "cloud.laz")
    r = geoortho.copc(source, tmp_path / "cloud.copc.laz")
    a, b = laspy.read(source), laspy.read(r.output)
    assert r.n_points == len(a.points) == len(b.points) and r.crs == "EPSG:32629"
    assert np.array_equal(_rows(a), _rows(b)) and b.header.point_format.id == 7
    assert r.depth >= 1 and r.n_nodes > 1 + r.depth
    with laspy.CopcReader.open(r.output) as reader:
        levels = [len(reader.query(level=d)) for d in range(r.depth + 1)]
        assert sum(levels) == r.n_points == len(reader.query())
        # the root is an even thinning of the whole site: every 50 m square has points in it
        root = reader.query(level=0)
        cells = set(zip((np.asarray(root.x) - 483_000) // 50, (np.asarray(root.y) - 4_288_000) // 50))
        assert len(cells) == 12 and levels[0] < 0.5 * r.n_points
        # a box query gives the points in the box, no more, no fewer
        lo, hi = np.array([483_060.0, 4_288_040.0]), np.array([483_130.0, 4_288_090.0])
        got = reader.query(bounds=laspy.copc.Bounds(mins=lo, maxs=hi))
        inside = (a.x >= lo[0]) & (a.x <= hi[0]) & (a.y >= lo[1]) & (a.y <= hi[1])
        got_inside = (got.x >= lo[0]) & (got.x <= hi[0]) & (got.y >= lo[1]) & (got.y <= hi[1])
        assert int(got_inside.sum()) == int(inside.sum())


def test_the_crs_is_a_header_vlr_where_qgis_looks_for_it(tmp_path):
    """copc-lib writes the WKT after the points (an extended VLR); QGIS reads the header's VLRs
    only, and showed the cloud without a CRS."""
    r = geoortho.copc(_cloud(tmp_path / "c.laz", n=5_000), tmp_path / "c.copc.laz")
    with laspy.open(r.output) as f:
        vlrs = {(v.user_id, v.record_id) for v in f.header.vlrs}
        assert ("LASF_Projection", 2112) in vlrs and ("copc", 1) in vlrs
        assert f.header.parse_crs().to_epsg() == 32629
        head = open(r.output, "rb").read(375)
        assert struct.unpack_from("<II", head, 96)[1] == len(f.header.vlrs)


def test_a_cloud_without_a_crs_takes_the_one_given(tmp_path):
    source = _cloud(tmp_path / "local.laz", n=5_000, crs=None)
    r = geoortho.copc(source, tmp_path / "local.copc.laz", crs="EPSG:32629")
    assert r.crs == "EPSG:32629" and laspy.read(r.output).header.parse_crs().to_epsg() == 32629


def test_bad_names_are_refused_before_any_work(tmp_path):
    source = _cloud(tmp_path / "c.laz", n=1_000)
    with pytest.raises(InputError, match="copc.laz"):
        geoortho.copc(source, tmp_path / "c.laz2")
    (tmp_path / "c.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match="LAS or LAZ"):
        geoortho.copc(tmp_path / "c.txt", tmp_path / "t.copc.laz")


def test_dem_writes_the_classified_cloud_as_copc_when_named_so(tmp_path):
    """Issue 80: the classified cloud too, ground as class 2, in a file QGIS streams."""
    source = _cloud(tmp_path / "c.laz", n=40_000)
    r = geoortho.dem(source, tmp_path / "dsm.tif", dtm=tmp_path / "dtm.tif", classified=tmp_path / "c.copc.laz")
    out = laspy.read(r.classified)
    assert len(out.points) == 40_000 and out.header.parse_crs().to_epsg() == 32629
    with laspy.open(r.classified) as f:
        assert ("copc", 1) in {(v.user_id, v.record_id) for v in f.header.vlrs}
    ground = np.asarray(out.classification) == 2
    on_block = (np.abs(np.asarray(out.x) - 483_100) < 13) & (np.abs(np.asarray(out.y) - 4_288_075) < 8)
    assert ground[~on_block].mean() > 0.95 and ground[on_block].mean() < 0.05
    assert sorted(p.name for p in tmp_path.iterdir() if "laz" in p.name) == ["c.copc.laz", "c.laz"]
