"""Reading an ``sfm`` output folder: its registered photos posed in its CRS (or another), its
sparse points, and the photos that could not be used. Used by dense, footprints and ortho."""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Literal, overload

import numpy as np
from pyproj import CRS

from geoortho.core.camera import Intrinsics, Pose, PosedCamera
from geoortho.core.colmap import load_pycolmap
from geoortho.core.crs import heights_from_text, parse_crs, transformer
from geoortho.errors import InputError

__all__ = ["cameras_from_sfm"]


def _intrinsics_from_colmap(cam: Any) -> Intrinsics:
    """COLMAP camera → our Intrinsics. COLMAP puts pixel (0, 0) at the top-left *corner*:
    its principal point is ours + 0.5."""
    p = [float(v) for v in cam.params]
    model = cam.model_name
    w, h = int(cam.width), int(cam.height)
    dist: tuple[float, ...]
    if model == "SIMPLE_PINHOLE":
        f, cx, cy, dist = p[0], p[1], p[2], ()
    elif model == "PINHOLE":
        f, cx, cy, dist = (p[0] + p[1]) / 2, p[2], p[3], ()
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, dist = p[0], p[1], p[2], (p[3], 0.0, 0.0, 0.0, 0.0)
    elif model == "RADIAL":
        f, cx, cy, dist = p[0], p[1], p[2], (p[3], p[4], 0.0, 0.0, 0.0)
    elif model == "OPENCV":
        # Square pixels assumed: fx and fy of a drone camera differ by far less than a pixel over the frame.
        f, cx, cy, dist = (p[0] + p[1]) / 2, p[2], p[3], (p[4], p[5], p[6], p[7], 0.0)
    else:
        raise InputError(
            f"COLMAP camera model {model} is not supported for orthorectification "
            "(use SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL or OPENCV)"
        )
    return Intrinsics(w, h, f, cx - 0.5, cy - 0.5, distortion=dist)


def _find_photo(images: Path, name: str, by_name: dict[str, Path]) -> Path | None:
    p = images / name
    if p.is_file():
        return p
    return by_name.get(Path(name).name)


@overload
def cameras_from_sfm(
    sfm_dir: str | os.PathLike[str],
    images: str | os.PathLike[str] | None,
    crs: CRS | None = None,
    *,
    local_frame_ok: Literal[False] = False,
) -> tuple[list[PosedCamera], CRS, np.ndarray, list[tuple[str, str]]]: ...


@overload
def cameras_from_sfm(
    sfm_dir: str | os.PathLike[str],
    images: str | os.PathLike[str] | None,
    crs: CRS | None = None,
    *,
    local_frame_ok: bool,
) -> tuple[list[PosedCamera], CRS | None, np.ndarray, list[tuple[str, str]]]: ...


def cameras_from_sfm(
    sfm_dir: str | os.PathLike[str],
    images: str | os.PathLike[str] | None,
    crs: CRS | None = None,
    *,
    local_frame_ok: bool = False,
) -> tuple[list[PosedCamera], CRS | None, np.ndarray, list[tuple[str, str]]]:
    """Registered photos of an ``sfm`` output, posed in its CRS (or ``crs``).

    Returns the cameras, the CRS, the georeferenced sparse points (N, 3) and the
    photos that could not be used with why. A model in a local frame (no CRS) is refused,
    unless ``local_frame_ok``: then the CRS returned is None and positions are the model's.
    """
    pycolmap = load_pycolmap()

    model, geo_path = _model_paths(sfm_dir)
    if not geo_path.is_file():
        raise InputError("no model/georeference.json: not an sfm output folder", path=sfm_dir)
    try:
        geo = json.loads(geo_path.read_text())
        rec = pycolmap.Reconstruction(str(model))
    except (ValueError, RuntimeError) as e:
        raise InputError(f"cannot read the SfM model: {e}", path=model) from None
    if not geo.get("crs") and not local_frame_ok:
        raise InputError(
            "the SfM model is in a local frame (no CRS): an orthophoto needs a georeferenced model", path=geo_path
        )
    model_crs = parse_crs(geo["crs"]) if geo.get("crs") else None
    offset = np.asarray(geo.get("offset", [0.0, 0.0, 0.0]), float)
    out_crs = model_crs if crs is None else crs
    move = None
    if model_crs is None and out_crs is not None:
        raise InputError("the SfM model is in a local frame (no CRS): it cannot be moved to a CRS", path=geo_path)
    if out_crs is not None and model_crs is not None and not out_crs.equals(model_crs):
        move = transformer(model_crs, out_crs)
    # without a photo folder (the dem's footprints need only the poses) no photo is looked for
    by_name = {p.name: p for p in Path(images).rglob("*") if p.is_file()} if images is not None else {}
    cams: list[PosedCamera] = []
    skipped: list[tuple[str, str]] = []
    for image_id in sorted(rec.reg_image_ids()):
        im = rec.image(image_id)
        path = _find_photo(Path(images), im.name, by_name) if images is not None else Path(im.name)
        if path is None:
            skipped.append((im.name, f"not found in {images}"))
            continue
        try:
            intr = _intrinsics_from_colmap(rec.camera(im.camera_id))
        except InputError as e:
            skipped.append((im.name, str(e)))
            continue
        cfw = im.cam_from_world() if callable(im.cam_from_world) else im.cam_from_world
        rot = np.asarray(cfw.rotation.matrix()).T  # world-from-camera
        centre = np.asarray(im.projection_center(), float) + offset
        if move is not None:
            centre, rot = _moved(move, centre, rot)
        cams.append(PosedCamera(intr, Pose(centre, rot), Path(im.name).name, path))
    pts = np.array([p.xyz for p in rec.points3D.values()], float).reshape(-1, 3) + offset
    if move is not None and len(pts):
        x, y, z = move.transform(pts[:, 0], pts[:, 1], pts[:, 2])
        pts = np.c_[x, y, z]
    return cams, out_crs, pts, skipped


def _model_paths(sfm_dir: str | os.PathLike[str]) -> tuple[Path, Path]:
    """An ``sfm`` output's COLMAP model folder (the folder itself when given the model) and its
    ``georeference.json``."""
    sfm_dir = Path(sfm_dir)
    model = sfm_dir / "model" if (sfm_dir / "model").is_dir() else sfm_dir
    return model, model / "georeference.json"


def model_heights(sfm_dir: str | os.PathLike[str]) -> tuple[CRS | str | None, str]:
    """The datum of an ``sfm`` output's heights (a vertical CRS, ``"ellipsoidal"``, or None: not
    known) and where the SfM learnt it (an older model that did not record it: None)."""
    try:
        geo = json.loads(_model_paths(sfm_dir)[1].read_text())
    except (OSError, ValueError):
        return None, "no georeference.json"
    return heights_from_text(geo.get("vertical_crs")), str(geo.get("vertical_crs_from") or "not recorded by the SfM")


def _moved(tr: Any, centre: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A pose carried into another projected CRS: the centre transformed, the rotation turned by the
    local grid convergence (finite differences over 10 m)."""
    c = np.array(tr.transform(*centre))
    ex = np.array(tr.transform(centre[0] + 10.0, centre[1], centre[2])) - c
    ey = np.array(tr.transform(centre[0], centre[1] + 10.0, centre[2])) - c
    ez = np.array(tr.transform(centre[0], centre[1], centre[2] + 10.0)) - c
    m = np.c_[ex, ey, ez] / 10.0
    u, _, vt = np.linalg.svd(m)  # nearest rotation: the scale change is not a turn
    return c, (u @ vt) @ rot
