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
from geoortho.products3d.view import side_by_side


@pytest.fixture(scope="module")
def made(tiny_survey, tmp_path_factory):
    from geoortho.products3d.mesh import mesh

    out = tmp_path_factory.mktemp("mesh")
    t = tiny_survey.truth
    r = mesh(t / "dsm.tif", t / "ortho.tif", out / "mesh.glb", obj=out / "mesh.obj",
             tileset=out / "tiles" / "tileset.json", view=out / "view.png", workers=1)  # fmt: skip
    return r, t


def _glb_mesh(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A glTF binary read back with pygltflib: vertices as written (glTF axes), faces, uv, texture;
    its primitives (the ground, the walls) as one, their textures side by side."""
    import cv2
    import pygltflib

    g = pygltflib.GLTF2().load_binary(str(path))
    blob = g.binary_blob()

    def view(accessor: int, dtype: type, width: int) -> np.ndarray:
        a = g.accessors[accessor]
        bv = g.bufferViews[a.bufferView]
        return np.frombuffer(blob, dtype, a.count * width, bv.byteOffset).reshape(a.count, width)

    parts = []
    for prim in g.meshes[0].primitives:
        pos = view(prim.attributes.POSITION, np.float32, 3).astype(float)
        uv = view(prim.attributes.TEXCOORD_0, np.float32, 2).astype(float)
        faces = view(prim.indices, np.uint32, 1).reshape(-1, 3).astype(np.int64)
        image = g.images[g.textures[g.materials[prim.material].pbrMetallicRoughness.baseColorTexture.index].source]
        bv = g.bufferViews[image.bufferView]
        jpeg = np.frombuffer(blob, np.uint8, bv.byteLength, bv.byteOffset)
        parts.append((pos, faces, uv, cv2.imdecode(jpeg, cv2.IMREAD_COLOR)[:, :, ::-1]))
    return side_by_side([p[:3] for p in parts], [p[3] for p in parts])


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
    assert r.wall_faces == 0 and r.n_vertices == len(xyz)  # no photos given: one part, the orthophoto's
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


def khronos_issues(glb: Path, tmp_path: Path) -> dict | None:
    """The Khronos glTF validator's report on a glTF binary (None where node or it is not installed)."""
    validator = Path(__file__).resolve().parents[1] / "tools" / "node_modules" / "gltf-validator"
    if shutil.which("node") is None or not validator.is_dir():
        return None
    script = tmp_path / "validate.js"
    script.write_text(
        "const v = require(process.argv[2]); const fs = require('fs');\n"
        "v.validateBytes(new Uint8Array(fs.readFileSync(process.argv[3])))"
        ".then(r => console.log(JSON.stringify(r.issues)), e => { console.error(e); process.exit(1); });\n"
    )
    p = subprocess.run(["node", str(script), str(validator), str(glb)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def test_the_glb_passes_the_khronos_validator(made, tmp_path):
    r, _ = made
    for glb in [r.output, next(r.tileset.parent.rglob("*.glb"))]:
        issues = khronos_issues(glb, tmp_path)
        if issues is None:
            pytest.skip("node or the glTF validator is not installed: sh tools/browser_setup.sh")
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


@pytest.fixture(scope="module", params=[4, 5], ids=["windows", "courses"])
def facades(request, tmp_path_factory):
    """A tiny survey whose buildings' walls are painted as facades (two styles, by the seed's parity)."""
    from geoortho.synthetic.survey import synth

    return synth(tmp_path_factory.mktemp("facades"), preset="tiny", seed=request.param, pathology="facades", workers=1)


def _on_facade(pts: np.ndarray, buildings: list[dict]) -> tuple[np.ndarray, np.ndarray]:
    """Points within 0.5 m of a building's outline (truth), and that building's eave height there."""
    near = np.zeros(len(pts), bool)
    eave = np.full(len(pts), np.nan)
    for b in buildings:
        a = np.radians(b["angle_deg"])
        dx, dy = pts[:, 0] - b["x"], pts[:, 1] - b["y"]
        u, v = dx * np.cos(a) + dy * np.sin(a), -dx * np.sin(a) + dy * np.cos(a)
        out_u, out_v = np.abs(u) - b["length_m"] / 2, np.abs(v) - b["width_m"] / 2
        on = (np.maximum(out_u, out_v) < 0.5) & (np.maximum(out_u, out_v) > -0.5)
        near |= on
        eave[on] = b["eave_m"]
    return near, eave


def test_walls_take_their_own_colours_from_the_photos(facades, tmp_path):
    """The walls' atlas, coloured from the photos that see them, against the facades' true colours:
    both styles' patterns (which change with the height, as no roof's do) are there, where the
    orthophoto's colours stretched down a wall have none of them."""
    from test_ortho import _true_cameras

    from geoortho.core.surface import read_surface
    from geoortho.products3d.mesh import mesh
    from geoortho.products3d.texture import ortho_texture
    from geoortho.products3d.walls import colour_under, photo_walls, wall_mask
    from geoortho.synthetic.scene import facade_colour

    t = facades.truth
    info = json.loads((t / "survey.json").read_text())["facades"]
    r = mesh(t / "dsm.tif", t / "ortho.tif", tmp_path / "m.glb", workers=1)
    xyz, faces, _, _ = _in_crs((r, t))
    wall = wall_mask(xyz, faces)
    bounds = (xyz[:, 0].min(), xyz[:, 1].min(), xyz[:, 0].max(), xyz[:, 1].max())
    ortho_rgb, _ = ortho_texture(t / "ortho.tif", bounds, 8192, 0.05)
    walls = photo_walls(xyz, faces[wall], _true_cameras(facades), read_surface(t / "dsm.tif"), {}, 0.05, 8192,
                        (ortho_rgb, bounds))  # fmt: skip
    assert walls is not None and walls.n_photos >= 2
    assert walls.photo_area_m2 > 0.5 * walls.area_m2  # nadir photos see most of a wall's face
    h, w = walls.image.shape[:2]
    screen = np.ascontiguousarray(walls.uv * (w, h) - 0.5)
    _, at = rasterize(screen, np.zeros(len(screen)), np.ascontiguousarray(walls.vertices, float),
                      np.ascontiguousarray(walls.faces, np.int64), h, w)  # fmt: skip
    drawn = np.isfinite(at[:, :, 0])
    pts = at[drawn]
    height_m = pts[:, 2] - read_surface(t / "dtm.tif").elevation(pts[:, 0], pts[:, 1])
    near, eave = _on_facade(pts, info["buildings"])
    facade = near & (height_m > 0.5) & (height_m < eave - 0.5)
    assert facade.sum() > 20_000
    true = facade_colour(info["style"], height_m, pts[:, 0], pts[:, 1]).mean(axis=1)[facade]
    stretched = colour_under(pts, ortho_rgb, bounds).astype(float)
    got = walls.image[drawn].astype(float)
    from_photo = facade & (np.abs(got - stretched).sum(axis=1) > 0)
    # the mean over each 0.2 m of height (the photos' texture and the rendering's noise averaged out)
    level = np.floor(height_m[facade] / 0.2).astype(np.int64)

    def profile(lum: np.ndarray) -> np.ndarray:
        return np.bincount(level, lum) / np.maximum(np.bincount(level), 1)

    kept = np.bincount(level) >= 200
    truth_profile = profile(true)[kept]
    corr_walls = np.corrcoef(profile(got.mean(axis=1)[facade])[kept], truth_profile)[0, 1]
    corr_stretched = np.corrcoef(profile(stretched.mean(axis=1)[facade])[kept], truth_profile)[0, 1]
    print(info["style"], facade.sum(), from_photo.sum(), kept.sum(), corr_walls, corr_stretched)
    assert corr_walls > 0.85 and corr_walls > corr_stretched + 0.4
