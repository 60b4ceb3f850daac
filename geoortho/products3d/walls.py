"""A mesh's walls coloured from the photos that see them.

Seen from above a wall is a line: the orthophoto has no colour for it. Its faces (steeper than
:data:`WALL_SLOPE_DEG`) are laid out on a texture atlas of their own, and each atlas texel is
coloured from one photo, chosen as the orthophoto chooses: the one that sees the face most
directly, with its line of sight to the face tested against the DSM. A run of faces that face one
way on one object (a wall's side, a crown's flank) takes one photo, the one that sees them best in
all, so that a facade is not a patchwork; a face that photo does not see takes its own best. The
photo's colours are scaled by the orthophoto's own gain for it (its report's ``gains_bgr``), so
walls and roofs match.

The atlas: each such run flattened onto its own upright plane (a wall is one already) and the
runs' boxes packed in shelves. Not ``xatlas``: on toledo's 300,000 wall faces (its crowns' flanks)
it took 21 s a pass to pack the same charts (and minutes to cut its own), where the shelves take
under a second; upright strips waste little of their boxes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from geoortho.core.camera import PosedCamera
from geoortho.core.surface import GridSurface
from geoortho.products3d.raster_mesh import rasterize, used_vertices
from geoortho.products3d.texture import Bounds, uv_of

#: A face steeper than this is a wall (a 2.5D mesh's roof or bank is rarely over 60 degrees).
WALL_SLOPE_DEG = 60.0
#: A photo sees a face only from in front of it, at most this far off its normal.
MAX_VIEW_ANGLE_DEG = 80.0
#: A line of sight may meet the DSM this many cells short of the face (the mesh is within about
#: a cell of the DSM, and a wall's foot is where the ray meets the ground).
SIGHT_TOLERANCE_CELLS = 2.0
#: The lens' cone a face is looked for in, this much wider than the frame's diagonal (distortion).
CONE_MARGIN_DEG = 5.0
#: Photos tried for a face, in the order they face it, before it is left to the orthophoto.
MAX_TRIES = 4
#: Faces that face one way: their horizontal normals within one of this many sectors.
SECTORS = 8
#: The atlas' gutter round each chart, texels (bilinear sampling and the first mip levels).
PADDING_PX = 2


@dataclass(frozen=True)
class WallTexture:
    """The wall faces on their own atlas.

    ``vertices`` are in the DSM's CRS (one per chart corner: a vertex on a chart's edge is there
    once for each chart); ``faces`` index them; ``uv`` (0, 0) the image's top-left; ``image`` RGB."""

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    image: np.ndarray
    texel_m: float
    n_photos: int  # photos used
    area_m2: float  # the walls' area
    photo_area_m2: float  # of which coloured by a photo


def wall_mask(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Faces steeper than :data:`WALL_SLOPE_DEG` (vertices in metres)."""
    n, _ = _normals_and_areas(vertices, faces)
    return np.asarray(np.abs(n[:, 2]) < math.cos(math.radians(WALL_SLOPE_DEG)))


def _normals_and_areas(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each face's unit normal (up for a face counter-clockwise from above) and its area."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    n = np.cross(b - a, c - a)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.asarray(n / np.where(length > 0, length, 1.0)), 0.5 * length[:, 0]


def ortho_gains(ortho: Path) -> dict[str, np.ndarray]:
    """The orthophoto's colour gain for each photo (BGR), from its report; none when it has none."""
    report = Path(ortho).with_name(Path(ortho).stem + "_report.json")
    try:
        gains = json.loads(report.read_text(encoding="utf-8")).get("gains_bgr") or {}
    except (OSError, ValueError):
        return {}
    return {str(k): np.asarray(v, np.float32) for k, v in gains.items() if isinstance(v, list) and len(v) == 3}


def photo_walls(
    vertices: np.ndarray,
    faces: np.ndarray,
    cams: list[PosedCamera],
    surface: GridSurface,
    gains: dict[str, np.ndarray],
    texel_m: float,
    max_px: int,
    fallback: tuple[np.ndarray, Bounds],
) -> WallTexture | None:
    """The wall faces of a mesh (``vertices`` in the DSM's CRS, metres) on an atlas coloured from
    ``cams``' photos; None when the mesh has no wall. A texel no photo sees takes the colour of the
    ``fallback`` texture (the orthophoto over its bounds: west, south, east, north) under it."""
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components

    if not len(faces):
        return None
    v, f = used_vertices(vertices, faces)
    normal, area = _normals_and_areas(v, f)
    centre = v[f].mean(axis=1)

    cos_view = _facing(centre, normal, cams)  # (faces, cams), 0 where behind or out of frame
    # runs of faces on one object that face one way take the photo that sees them best in all
    m = len(f)
    rows = np.repeat(np.arange(m), 3)
    links = sparse.coo_matrix((np.ones(3 * m), (rows, f.ravel())), shape=(m, len(v))).tocsr()
    _, component = connected_components(links @ links.T, directed=False)
    sector = np.floor((np.arctan2(normal[:, 1], normal[:, 0]) + math.pi) / (2 * math.pi) * SECTORS).astype(np.int64)
    _, group = np.unique(component * SECTORS + np.clip(sector, 0, SECTORS - 1), return_inverse=True)
    weighted = np.zeros((group.max() + 1, len(cams)))
    np.add.at(weighted, group, cos_view * area[:, None])
    choice = _first_seen(centre, cams, surface, cos_view, np.argmax(weighted, axis=1)[group])

    av, af, auv, width, height, texel, photo = _atlas(v, f, normal, area, group, choice, texel_m, max_px)
    image = _colour(av, auv, af, photo, width, height, cams, gains, fallback, texel)
    seen = choice >= 0
    return WallTexture(
        av, af.astype(np.int32), auv, image, texel, len(set(choice[seen].tolist())),
        float(area.sum()), float(area[seen].sum()),
    )  # fmt: skip


def _atlas(
    v: np.ndarray,
    f: np.ndarray,
    normal: np.ndarray,
    area: np.ndarray,
    group: np.ndarray,
    choice: np.ndarray,
    texel_m: float,
    max_px: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int, float, np.ndarray]:
    """The faces' charts packed on an atlas of about ``texel_m`` a texel, at most ``max_px`` a side:
    (vertices, faces, uv, width, height, texel size, each vertex's photo).

    A chart is a group's faces that take one photo, flattened onto the upright plane across the
    group's mean normal (a wall's own plane; a crown's flank within a sector of it): an upright
    strip, whose box wastes little. The boxes are packed in shelves, tallest first, with a gutter
    of :data:`PADDING_PX` round each. Vertices are split by chart, so each carries its chart's photo."""
    photos = np.unique(choice)
    chart = group * len(photos) + np.searchsorted(photos, choice)
    _, chart = np.unique(chart, return_inverse=True)
    n_charts = int(chart.max()) + 1
    across = np.zeros((int(group.max()) + 1, 2))
    np.add.at(across, group, normal[:, :2] * area[:, None])
    across /= np.maximum(np.linalg.norm(across, axis=1, keepdims=True), 1e-12)
    keys, inverse = np.unique((f.astype(np.int64) * n_charts + chart[:, None]).ravel(), return_inverse=True)
    vertex, vertex_chart = keys // n_charts, keys % n_charts
    faces = inverse.reshape(-1, 3)
    first_face = np.zeros(n_charts, np.int64)
    first_face[chart[::-1]] = np.arange(len(chart))[::-1]  # any face of each chart: its group and photo
    vertex_group, photo = group[first_face[vertex_chart]], choice[first_face[vertex_chart]]
    points = v[vertex]
    along = np.stack([-across[vertex_group, 1], across[vertex_group, 0]], axis=1)
    flat = np.stack([(points[:, :2] * along).sum(axis=1), points[:, 2]], axis=1)
    low = np.full((n_charts, 2), np.inf)
    high = np.full((n_charts, 2), -np.inf)
    np.minimum.at(low, vertex_chart, flat)
    np.maximum.at(high, vertex_chart, flat)
    texel = texel_m
    while True:
        box = np.ceil((high - low) / texel).astype(np.int64) + 1 + 2 * PADDING_PX
        origin, width, height = _shelves(box, max_px)
        if width <= max_px and height <= max_px:
            break
        texel *= 1.1 * math.sqrt(max(width, height) / max_px)
    texels = (flat - low[vertex_chart]) / texel + PADDING_PX + origin[vertex_chart]
    uv = texels / (width, height)
    return points, faces, uv, width, height, texel, photo


def _shelves(box: np.ndarray, max_px: int) -> tuple[np.ndarray, int, int]:
    """Boxes (n, 2: width, height in texels) packed in rows, the tallest first, in a square about
    their total area: each box's (x, y) and the atlas' width and height."""
    width = max(
        int(box[:, 0].max()), min(max_px, int(math.ceil(math.sqrt(1.1 * float((box[:, 0] * box[:, 1]).sum())))))
    )
    origin = np.zeros_like(box)
    x = y = row_height = 0
    for i in np.argsort(-box[:, 1], kind="stable").tolist():
        w, h = int(box[i, 0]), int(box[i, 1])
        if x + w > width:
            x, y, row_height = 0, y + row_height, 0
        origin[i] = (x, y)
        x += w
        row_height = max(row_height, h)
    return origin, width, y + row_height


def _colour(
    vertices: np.ndarray,
    uv: np.ndarray,
    faces: np.ndarray,
    photo: np.ndarray,
    width: int,
    height: int,
    cams: list[PosedCamera],
    gains: dict[str, np.ndarray],
    fallback: tuple[np.ndarray, Bounds],
    texel_m: float,
) -> np.ndarray:
    """The atlas' texels coloured, each from its chart's photo (``photo`` -1: the fallback texture)."""
    centre = vertices.mean(axis=0)
    attrs = np.ascontiguousarray(np.column_stack([vertices - centre, photo]), np.float64)
    screen = np.ascontiguousarray(uv * (width, height) - 0.5, np.float64)
    _, out = rasterize(screen, np.zeros(len(screen)), attrs, np.ascontiguousarray(faces, np.int64), height, width,
                       dtype=np.float32)  # fmt: skip
    drawn = np.isfinite(out[:, :, 0])
    at = np.nonzero(drawn.ravel())[0]
    texels = out.reshape(-1, 4)[at]
    del out
    image = np.zeros((height * width, 3), np.uint8)
    which = np.rint(texels[:, 3]).astype(np.int64)
    order = np.argsort(which, kind="stable")
    photos = np.unique(which)
    starts = np.searchsorted(which[order], photos)
    for k, lo, hi in zip(photos, starts, [*starts[1:], len(order)]):
        idx = order[lo:hi]
        pts = texels[idx, :3].astype(np.float64) + centre
        cam = cams[int(k)] if k >= 0 else None
        image[at[idx]] = (
            colour_under(pts, *fallback) if cam is None else _from_photo(cam, pts, gains.get(cam.name), texel_m)
        )
    atlas = image.reshape(height, width, 3)
    _fill_gutters(atlas, drawn)
    return atlas


def _facing(centre: np.ndarray, normal: np.ndarray, cams: list[PosedCamera]) -> np.ndarray:
    """How directly each photo faces each face (the cosine of its view off the face's normal), 0
    where the face is behind it or out of its frame (its line of sight not tested)."""
    from geoortho.core.camera import in_frame

    cos_min = math.cos(math.radians(MAX_VIEW_ANGLE_DEG))
    out = np.zeros((len(centre), len(cams)), np.float32)
    for k, cam in enumerate(cams):
        to_cam = cam.pose.center - centre
        dist = np.maximum(np.linalg.norm(to_cam, axis=1), 1e-9)
        cos = np.einsum("ij,ij->i", to_cam, normal) / dist
        # the lens' cone first (a dot product a face), then the camera model for what is in it
        intr = cam.intrinsics
        half_diagonal = math.atan(math.hypot(intr.width_px, intr.height_px) / 2 / intr.focal_px)
        axis = cam.pose.rotation[:, 2]
        cone = -(to_cam @ axis) / dist > math.cos(min(half_diagonal + math.radians(CONE_MARGIN_DEG), math.pi / 2))
        idx = np.nonzero((cos > cos_min) & cone)[0]
        if not len(idx):
            continue
        px, depth = cam.project(centre[idx])
        ok = (depth > 0) & np.asarray(in_frame(px[:, 0], px[:, 1], intr.width_px, intr.height_px))
        out[idx[ok], k] = cos[idx[ok]]
    return out


def _first_seen(
    centre: np.ndarray, cams: list[PosedCamera], surface: GridSurface, cos_view: np.ndarray, first: np.ndarray
) -> np.ndarray:
    """Each face's photo: ``first`` where its line of sight is clear, else the next that faces it
    most directly and sees it (:data:`MAX_TRIES` tried in all); -1 where none does. A line of
    sight is marched for the photos tried only (a photo per face, not every photo)."""
    cos_view = cos_view.copy()
    chosen = np.full(len(centre), -1, np.int64)
    todo, candidate = np.arange(len(centre)), first
    for _ in range(MAX_TRIES):
        # a face its run's photo does not face takes the one that faces it best
        other = cos_view[todo, candidate] <= 0
        candidate = candidate.copy()
        candidate[other] = np.argmax(cos_view[todo[other]], axis=1)
        facing = cos_view[todo, candidate] > 0
        todo, candidate = todo[facing], candidate[facing]
        if not len(todo):
            break
        seen = np.zeros(len(todo), bool)
        for k in np.unique(candidate):
            these = np.nonzero(candidate == k)[0]
            seen[these] = _in_sight(cams[int(k)], centre[todo[these]], surface)
        chosen[todo[seen]] = candidate[seen]
        cos_view[todo[~seen], candidate[~seen]] = 0
        todo = todo[~seen]
        candidate = np.argmax(cos_view[todo], axis=1) if len(todo) else candidate[:0]
    return chosen


def _in_sight(cam: PosedCamera, points: np.ndarray, surface: GridSurface) -> np.ndarray:
    """Whether the camera's lines of sight to ``points`` reach them (or end within
    :data:`SIGHT_TOLERANCE_CELLS` of them) before the DSM."""
    to_cam = cam.pose.center - points
    dist = np.linalg.norm(to_cam, axis=1)
    dirs = -to_cam / dist[:, None]
    hits = surface.intersect(np.broadcast_to(cam.pose.center, dirs.shape), dirs, max_range_m=float(dist.max()) + 10)
    return np.asarray(~hits.hit | (hits.range_m >= dist - SIGHT_TOLERANCE_CELLS * surface.cell_m))


def _from_photo(cam: PosedCamera, pts: np.ndarray, gain_bgr: np.ndarray | None, texel_m: float) -> np.ndarray:
    """The photo's colour (RGB uint8) at world points, scaled by the orthophoto's gain for it; read
    at 1/2, 1/4 or 1/8 of its size where its pixels there are that much finer than ``texel_m``."""
    from geoortho.orthophoto.seams import read_photo_bgr

    px, depth = cam.project(pts)
    photo_m = float(np.median(depth)) / cam.intrinsics.focal_px
    reduction = max([r for r in (1, 2, 4, 8) if r * photo_m <= texel_m] or [1])
    scale = 1.0 / reduction  # pixel centres: (x + 0.5) / r - 0.5
    sampled = _sample(read_photo_bgr(str(cam.file), reduction), (px[:, 0] + 0.5) * scale - 0.5,
                      (px[:, 1] + 0.5) * scale - 0.5)  # fmt: skip
    if gain_bgr is not None:
        sampled = np.clip(sampled.astype(np.float32) * gain_bgr, 0, 255).astype(np.uint8)
    return np.asarray(sampled[:, ::-1])


def colour_under(pts: np.ndarray, texture: np.ndarray, bounds: Bounds) -> np.ndarray:
    """The colour of a north-up texture over ``bounds`` under world points."""
    h, w = texture.shape[:2]
    at = uv_of(pts, bounds) * (w, h) - 0.5
    return _sample(texture, at[:, 0], at[:, 1])


def _sample(image: np.ndarray, col: np.ndarray, row: np.ndarray) -> np.ndarray:
    """An image's colours at (col, row), bilinear (a list of points laid out as rows of
    :data:`_ROW`: OpenCV's remap takes at most 32,767 a side)."""
    import cv2

    n = len(col)
    rows = max(-(-n // _ROW), 1)
    grid = np.full((2, rows * _ROW), -1.0, np.float32)
    grid[0, :n], grid[1, :n] = col, row
    out = cv2.remap(image, grid[0].reshape(rows, _ROW), grid[1].reshape(rows, _ROW), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)  # fmt: skip
    return np.asarray(out.reshape(rows * _ROW, -1)[:n])


_ROW = 4096


def _fill_gutters(image: np.ndarray, filled: np.ndarray) -> None:
    """The gutters round the charts take their edges' colours, :data:`PADDING_PX` texels out and
    one more (bilinear sampling reads across a chart's edge); the atlas' unused rest, its mean
    colour (the coarser mip levels average it in)."""
    import cv2

    if filled.all() or not filled.any():
        return
    image[~filled] = image[filled].mean(axis=0).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    mask = filled.astype(np.uint8)
    for _ in range(PADDING_PX + 1):
        grown = cv2.dilate(mask, kernel)
        new = (grown > 0) & (mask == 0)
        if not new.any():
            break
        # each new texel: its charted neighbours' colour (their largest, a channel at a time)
        image[new] = cv2.dilate(image * mask[:, :, None], kernel)[new]
        mask = np.asarray(grown, np.uint8)


def wall_summary(walls: WallTexture | None) -> tuple[int, float]:
    """The walls' faces, and the share of their area coloured by a photo (NaN without walls)."""
    if walls is None:
        return 0, math.nan
    return len(walls.faces), walls.photo_area_m2 / walls.area_m2 if walls.area_m2 > 0 else math.nan
