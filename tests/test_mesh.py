"""The textured mesh (issue 80): its heights against the true DSM, its walls against the true
outlines, its texture seen from above against the orthophoto, its files read back by other
readers, and the 3D Tiles placed on the Earth where the DSM is."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from pyproj import CRS, Transformer
from scipy import ndimage
from scipy.spatial import cKDTree

from geoortho.products3d.raster_mesh import draw_heights, rasterize


@pytest.fixture(scope="module")
def made(tiny_survey, tmp_path_factory):
    from geoortho.products3d.mesh import mesh

    out = tmp_path_factory.mktemp("mesh")
    t = tiny_survey.truth
    r = mesh(t / "dsm.tif", t / "ortho.tif", out / "mesh.glb", obj=out / "mesh.obj",
             tileset=out / "tiles" / "tileset.json", view=out / "view.png", workers=1)  # fmt: skip
    return r, t


def _glb_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A glTF binary read back with pygltflib: vertices as written (glTF axes), faces, uv, texture."""
    import cv2
    import pygltflib

    g = pygltflib.GLTF2().load_binary(str(path))
    blob = g.binary_blob()

    def view(accessor: int, dtype: type, width: int) -> np.ndarray:
        a = g.accessors[accessor]
        bv = g.bufferViews[a.bufferView]
        return np.frombuffer(blob, dtype, a.count * width, bv.byteOffset).reshape(a.count, width)

    prim = g.meshes[0].primitives[0]
    pos = view(prim.attributes.POSITION, np.float32, 3).astype(float)
    uv = view(prim.attributes.TEXCOORD_0, np.float32, 2).astype(float)
    faces = view(prim.indices, np.uint32, 1).reshape(-1, 3).astype(np.int64)
    bv = g.bufferViews[g.images[0].bufferView]
    jpeg = np.frombuffer(blob, np.uint8, bv.byteLength, bv.byteOffset)
    texture = cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[:, :, ::-1]
    return pos, faces, uv, texture


def _in_crs(made) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    r, _ = made
    pos, faces, uv, texture = _glb_mesh(r.output)
    georef = json.loads(r.georeference.read_text())
    x0, y0, z0 = georef["offset"]
    xyz = np.stack([pos[:, 0] + x0, -pos[:, 2] + y0, pos[:, 1] + z0], axis=1)  # glTF: x east, y up, z south
    return xyz, faces, uv, texture


def _truth(path: Path) -> tuple[np.ndarray, rasterio.Affine]:
    with rasterio.open(path) as ds:
        return ds.read(1, masked=True).astype(float).filled(np.nan), ds.transform


def test_the_mesh_is_the_true_surface_within_the_error_it_states(made):
    r, truth = made
    xyz, faces, _, _ = _in_crs(made)
    dsm, t = _truth(truth / "dsm.tif")
    drawn = draw_heights(xyz, faces, t.c + t.a / 2, t.f + t.e / 2, t.a, *dsm.shape)
    d = drawn - dsm
    ok = np.isfinite(dsm)
    assert np.isfinite(d[ok]).mean() > 0.995  # the mesh covers the DSM
    rmse = float(np.sqrt(np.nanmean(d[ok] ** 2)))
    # re-measured from the file, it is the figure stated; and within the error asked
    assert rmse == pytest.approx(r.rmse_m, rel=0.05, abs=0.002)
    assert rmse <= r.max_rmse_m == pytest.approx(t.a)  # one cell, by default
    # thinned where flat: far fewer faces than the grid's two a cell
    assert r.n_faces < 0.25 * 2 * ok.sum()
    assert r.faces_per_ha > 0 and r.mb_per_ha > 0


def test_walls_stand_within_a_cell_of_the_true_outlines(made):
    _, truth = made
    xyz, faces, _, _ = _in_crs(made)
    dsm, t = _truth(truth / "dsm.tif")
    dtm, _ = _truth(truth / "dtm.tif")
    drawn = draw_heights(xyz, faces, t.c + t.a / 2, t.f + t.e / 2, t.a, *dsm.shape)
    true_object = (dsm - dtm) > 2.0
    mesh_object = (drawn - dtm) > 2.0
    assert true_object.sum() > 500  # the survey has a building and trees
    # the walls: where the truth steps by more than 2 m from a cell to the next (a crown's gentle
    # foot is no wall: its 2 m contour moves cells for centimetres of height)
    wall = true_object & (ndimage.minimum_filter(dsm, size=3) < dsm - 2.0)
    assert wall.sum() > 50
    near_walls = ndimage.binary_dilation(wall, iterations=4)
    wrong = (true_object ^ mesh_object) & near_walls
    # every cell on the wrong side of 2 m beside a wall is at most one cell from the true outline
    outline = true_object ^ ndimage.binary_erosion(true_object)
    cells_from_outline = ndimage.distance_transform_edt(~outline)
    assert cells_from_outline[wrong].max() <= 1.5
    # and few: a wall is one cell wide, not a ramp
    assert wrong.sum() < 0.6 * (outline & near_walls).sum()


def test_the_texture_seen_from_above_is_the_orthophoto(made):
    import cv2

    _, truth = made
    xyz, faces, uv, texture = _in_crs(made)
    with rasterio.open(truth / "ortho.tif") as o:
        ortho = np.moveaxis(o.read([1, 2, 3]), 0, -1).astype(float)
        seen = o.read_masks(1) > 0
        ot = o.transform
    # the mesh drawn from above on the orthophoto's grid, each pixel its texture's colour
    screen = np.stack([(xyz[:, 0] - ot.c) / ot.a - 0.5, (xyz[:, 1] - ot.f) / ot.e - 0.5], axis=1)
    _, at = rasterize(np.ascontiguousarray(screen), -xyz[:, 2].copy(), np.ascontiguousarray(uv), faces, *seen.shape)
    drawn = np.isfinite(at[:, :, 0])
    mx = (at[:, :, 0] * texture.shape[1] - 0.5).astype(np.float32)
    my = (at[:, :, 1] * texture.shape[0] - 0.5).astype(np.float32)
    colour = cv2.remap(texture, mx, my, cv2.INTER_LINEAR).astype(float)
    inside = drawn & ndimage.binary_erosion(seen, iterations=3)
    assert inside.mean() > 0.5
    diff = np.abs(colour - ortho)[inside]
    # the JPEG's and the resampling's loss alone (a texture offset by a pixel: about 25 DN here)
    assert float(np.median(diff)) <= 4.0 and float(diff.mean()) <= 8.0


def test_the_obj_and_its_texture_are_read_back(made):
    import trimesh

    r, _ = made
    obj = trimesh.load(r.obj, force="mesh")
    assert len(obj.faces) == r.n_faces
    head = r.obj.read_text().splitlines()[:6]
    assert any("offset:" in ln and str(r.offset[0]) in ln for ln in head)
    assert (r.obj.with_suffix(".mtl")).is_file() and (r.obj.with_suffix(".jpg")).stat().st_size > 1000
    # OBJ is z-up, east and north as the CRS
    xyz, _, _, _ = _in_crs(made)
    assert obj.bounds[:, 2] == pytest.approx([xyz[:, 2].min() - r.offset[2], xyz[:, 2].max() - r.offset[2]], abs=1e-3)


def test_the_tileset_is_placed_on_the_earth_where_the_dsm_is(made):
    r, _ = made
    ts = json.loads(r.tileset.read_text())
    assert ts["asset"]["version"] == "1.1"
    root = ts["root"]
    m = np.array(root["transform"]).reshape(4, 4).T  # column-major
    crs = CRS.from_user_input(r.crs)
    from_ecef = Transformer.from_crs(CRS.from_epsg(4978), crs.to_3d(), always_xy=True)
    site = cKDTree(_in_crs(made)[0])
    seen_levels, n_content = set(), 0

    def walk(tile: dict, depth: int, parent_error: float) -> None:
        nonlocal n_content
        assert tile["geometricError"] <= parent_error + 1e-9  # finer down the tree
        if "children" not in tile:
            assert tile["geometricError"] == 0
        if "content" in tile:
            n_content += 1
            seen_levels.add(depth)
            pos, faces, _, _ = _glb_mesh(r.tileset.parent / tile["content"]["uri"])
            enu = np.stack([pos[:, 0], -pos[:, 2], pos[:, 1]], axis=1)  # glTF y-up to the tile's z-up
            box = np.array(tile["boundingVolume"]["box"])
            assert np.all(np.abs(enu - box[:3]) <= np.array([box[3], box[7], box[11]]) + 0.05)
            ecef = (m[:3, :3] @ enu.T).T + m[:3, 3]
            x, y, z = from_ecef.transform(ecef[:, 0], ecef[:, 1], ecef[:, 2])
            if depth == 0:  # the finest tiles are the site mesh's own: every vertex found back on it,
                # through the Earth frame, to a millimetre
                gap, _ = site.query(np.stack([np.asarray(x), np.asarray(y), np.asarray(z)], axis=1))
                assert gap.max() < 0.001
        for child in tile.get("children", []):
            walk(child, depth - 1, tile["geometricError"])

    walk(root, r.n_levels - 1, ts["geometricError"])
    assert n_content == r.n_tiles and seen_levels == set(range(r.n_levels)) and r.n_levels >= 2


def test_the_oblique_view_shows_the_mesh(made):
    import cv2

    r, _ = made
    img = cv2.imread(str(r.view))
    assert img is not None and img.shape[1] == 1600
    drawn = (img < 250).any(axis=2)
    assert 0.2 < drawn.mean() < 0.9 and img[drawn].std() > 10  # a textured picture, not a blank


@pytest.mark.skipif(shutil.which("node") is None, reason="node is not installed")
def test_the_glb_passes_the_khronos_validator(made, tmp_path):
    r, _ = made
    validator = Path(__file__).resolve().parents[1] / "tools" / "node_modules" / "gltf-validator"
    if not validator.is_dir():
        pytest.skip("the glTF validator is not installed: sh tools/browser_setup.sh")
    script = tmp_path / "validate.js"
    script.write_text(
        "const v = require(process.argv[2]); const fs = require('fs');\n"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[3])))"
        ".then(r => console.log(JSON.stringify(r.issues)), e => { console.error(e); process.exit(1); });\n"
    )
    for glb in [r.output, next(r.tileset.parent.rglob("*.glb"))]:
        p = subprocess.run(["node", str(script), str(validator), str(glb)], capture_output=True, text=True, timeout=120)
        assert p.returncode == 0, p.stderr
        issues = json.loads(p.stdout)
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]


def test_mesh_refuses_an_orthophoto_of_another_crs(made, tmp_path):
    r, truth = made
    other = tmp_path / "ortho_wrong.tif"
    with rasterio.open(truth / "ortho.tif") as o:
        profile = {**o.profile, "crs": "EPSG:32630"}
        data = o.read()
    with rasterio.open(other, "w", **profile) as w:
        w.write(data)
    p = subprocess.run([sys.executable, "-m", "geoortho", "mesh", "--dsm", str(truth / "dsm.tif"), "--ortho",
                        str(other), "--output", str(tmp_path / "m.glb")], capture_output=True, text=True)  # fmt: skip
    assert p.returncode == 2 and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "ortho_wrong.tif" in p.stderr and "CRS" in p.stderr
    assert not list(tmp_path.glob("*.glb"))
