"""Cesium 3D Tiles (1.1): a ``tileset.json`` whose tiles are glTF binaries, placed on the Earth.

The tileset's root carries the one transform, from a local east-north-up frame at the site's
centre to Earth-centred coordinates (EPSG:4978); every tile's vertices are in that frame, turned
from the DSM's CRS through geographic coordinates by pyproj (a projected grid's north is not
true north: at a UTM zone's edge the two differ by 2 degrees, 17 m at 500 m from the centre).
Heights are taken as heights above the ellipsoid of the CRS's datum unless the CRS is compound
with a vertical datum pyproj can turn (a geoid's grid).

The file is written by hand, as the plain JSON it is: py3dtiles' tile writer is made for point
clouds (its mesh path needs b3dm), and 3D Tiles 1.1 takes a glTF binary as a tile's content as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pyproj import CRS, Transformer


@dataclass(frozen=True)
class LocalFrame:
    """East, north, up at ``origin_ecef``: ``rotation`` rows are the east, north and up axes in
    Earth-centred coordinates."""

    origin_ecef: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3)
    lon_deg: float
    lat_deg: float
    height_m: float

    def matrix(self) -> list[float]:
        """The local-to-Earth 4x4 transform, column-major (the tileset's ``transform``)."""
        m = np.eye(4)
        m[:3, :3] = self.rotation.T
        m[:3, 3] = self.origin_ecef
        return [float(v) for v in m.T.ravel()]


def _ecef_transformer(crs: CRS) -> Transformer:
    return Transformer.from_crs(crs.to_3d() if not crs.is_compound else crs, CRS.from_epsg(4978), always_xy=True)


def local_frame(crs: CRS, x: float, y: float, z: float) -> LocalFrame:
    """The east-north-up frame at a point of the CRS."""
    to_geo = Transformer.from_crs(crs.to_3d() if not crs.is_compound else crs, CRS.from_epsg(4979), always_xy=True)
    lon, lat, h = to_geo.transform(x, y, z)
    origin = np.array(_ecef_transformer(crs).transform(x, y, z), float)
    lo, la = np.radians(lon), np.radians(lat)
    east = np.array([-np.sin(lo), np.cos(lo), 0.0])
    north = np.array([-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)])
    up = np.array([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
    return LocalFrame(origin, np.stack([east, north, up]), float(lon), float(lat), float(h))


def to_local(frame: LocalFrame, crs: CRS, xyz: np.ndarray) -> np.ndarray:
    """Points of the CRS (n, 3) in the frame's east, north, up (metres)."""
    ex, ey, ez = _ecef_transformer(crs).transform(xyz[:, 0], xyz[:, 1], xyz[:, 2])
    d = np.stack([np.asarray(ex), np.asarray(ey), np.asarray(ez)], axis=1) - frame.origin_ecef
    enu: np.ndarray = d @ frame.rotation.T
    return enu


@dataclass
class Tile:
    """A tile of the tileset: its content's file (relative to the tileset), its box in the local
    frame, its geometric error (metres: what is wrong on screen if it is drawn and its children
    are not) and its children."""

    content: str | None
    lo: np.ndarray  # (3,) east, north, up
    hi: np.ndarray
    geometric_error: float
    children: list[Tile] = field(default_factory=list)

    def as_json(self) -> dict[str, Any]:
        centre = (self.lo + self.hi) / 2
        half = np.maximum((self.hi - self.lo) / 2, 0.01)
        out: dict[str, Any] = {
            "boundingVolume": {
                "box": [
                    *map(float, centre),
                    float(half[0]),
                    0.0,
                    0.0,
                    0.0,
                    float(half[1]),
                    0.0,
                    0.0,
                    0.0,
                    float(half[2]),
                ]
            },  # fmt: skip
            "geometricError": round(float(self.geometric_error), 4),
            "refine": "REPLACE",
        }
        if self.content is not None:
            out["content"] = {"uri": self.content}
        if self.children:
            out["children"] = [c.as_json() for c in self.children]
        return out


def tileset_json(root: Tile, frame: LocalFrame, extras: dict[str, Any]) -> dict[str, Any]:
    """The tileset: ``root`` placed on the Earth by the frame's transform."""
    body = root.as_json()
    body["transform"] = frame.matrix()
    span = float(np.linalg.norm(root.hi - root.lo))
    return {
        "asset": {"version": "1.1", "generator": "geoortho", "extras": extras},
        "geometricError": round(max(span, root.geometric_error), 4),
        "root": body,
    }
