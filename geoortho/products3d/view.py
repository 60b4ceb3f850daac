"""An oblique picture of a textured mesh, drawn on the CPU (no OpenGL here, nor on a QGIS server):
a parallel projection from the south-west, each pixel the nearest face's texture, lit by its
slope so that walls and roofs read as solids."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from geoortho.products3d.gltf import Part
from geoortho.products3d.raster_mesh import rasterize

#: The viewer's direction: from the south-west, looking down at this angle (degrees).
AZIMUTH_DEG = 225.0
ELEVATION_DEG = 40.0
#: The light: from the north-west, as a hillshade's, high.
LIGHT = np.array([-0.5, 0.5, 0.9]) / np.linalg.norm([-0.5, 0.5, 0.9])
#: Each texture at most this many pixels a side in the picture.
VIEW_TEXTURE_PX = 2048


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted normals at the vertices (unit; up where no face meets)."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    fn = np.cross(b - a, c - a)
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return np.where(norm > 0, vn / np.where(norm > 0, norm, 1.0), [0.0, 0.0, 1.0])


def render_oblique(parts: Sequence[Part], textures: Sequence[np.ndarray], width_px: int = 1600) -> np.ndarray:
    """The mesh's parts (east, north, up in metres) seen obliquely, each with its texture (RGB):
    an (h, w, 3) uint8 RGB picture, white where nothing is drawn."""

    # a picture 1,600 px wide shows no texture finer than this (an 8,192 px atlas cost 0.4 GB here)
    textures = [_at_most(t, VIEW_TEXTURE_PX) for t in textures]
    # the parts drawn at once (one depth buffer)
    vertices, faces, uv, texture = side_by_side([(p.enu, p.faces, p.uv) for p in parts], textures)
    return _render(vertices, faces, uv, texture, width_px)


def side_by_side(
    pieces: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]], textures: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Textured pieces (vertices, faces, uv; each with its texture) as one: their vertices and faces
    joined, their textures side by side in one image and their uv moved onto it."""
    height = max(t.shape[0] for t in textures)
    width = sum(t.shape[1] for t in textures)
    texture = np.zeros((height, width, 3), np.uint8)
    vertices, faces, uv, base, left = [], [], [], 0, 0
    for (v, f, t_uv), tex in zip(pieces, textures):
        texture[: tex.shape[0], left : left + tex.shape[1]] = tex
        vertices.append(v)
        faces.append(f + base)
        uv.append(np.column_stack([(t_uv[:, 0] * tex.shape[1] + left) / width, t_uv[:, 1] * tex.shape[0] / height]))
        base += len(v)
        left += tex.shape[1]
    return np.concatenate(vertices), np.concatenate(faces), np.concatenate(uv), texture


def _at_most(texture: np.ndarray, side_px: int) -> np.ndarray:
    import cv2

    scale = side_px / max(texture.shape[:2])
    if scale >= 1.0:
        return texture
    size = (max(1, round(texture.shape[1] * scale)), max(1, round(texture.shape[0] * scale)))
    return np.asarray(cv2.resize(texture, size, interpolation=cv2.INTER_AREA))


def _render(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, texture: np.ndarray, width_px: int) -> np.ndarray:
    import cv2

    az, el = np.radians(AZIMUTH_DEG), np.radians(ELEVATION_DEG)
    # from the viewer into the scene: from the south-west means looking north-east, and down
    look = np.array([-np.sin(az) * np.cos(el), -np.cos(az) * np.cos(el), -np.sin(el)])
    right = np.array([np.cos(az), -np.sin(az), 0.0]) * -1.0
    right /= np.linalg.norm(right)
    upv = np.cross(right, look)
    sx, sy, depth = vertices @ right, -(vertices @ upv), vertices @ look
    span = max(float(np.ptp(sx)), 1e-6)
    scale = (width_px - 1) / span
    px = (sx - sx.min()) * scale
    py = (sy - sy.min()) * scale
    height_px = int(np.ceil(float(py.max()))) + 1
    shade = np.clip(vertex_normals(vertices, faces) @ LIGHT, 0.0, 1.0) * 0.45 + 0.55
    attrs = np.ascontiguousarray(np.column_stack([uv, shade]), np.float64)
    screen = np.ascontiguousarray(np.column_stack([px, py]), np.float64)
    _, out = rasterize(screen, np.ascontiguousarray(depth), attrs, np.ascontiguousarray(faces, np.int64),
                       height_px, width_px)  # fmt: skip
    drawn = np.isfinite(out[:, :, 0])
    th, tw = texture.shape[:2]
    map_x = np.where(drawn, out[:, :, 0] * tw - 0.5, -1).astype(np.float32)
    map_y = np.where(drawn, out[:, :, 1] * th - 0.5, -1).astype(np.float32)
    colour = cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    lit = colour.astype(np.float32) * np.where(drawn, out[:, :, 2], 1.0)[:, :, None]
    return np.where(drawn[:, :, None], np.clip(lit, 0, 255), 255).astype(np.uint8)
