"""What gcp-find writes: OpenDroneMap's gcp_list.txt, the detections table and the review sheet."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from pyproj import CRS

from geoortho.core.crs import crs_to_text, transformer
from geoortho.core.outputs import write_png, write_text, write_vector
from geoortho.core.styles import product_styles
from geoortho.gcp.io import GcpSet
from geoortho.gcp.verdicts import DETECTED, Observation


def write_gcp_list(path: Path, observations: list[Observation], gcps: GcpSet, crs: CRS) -> Path:
    """gcp_list.txt as OpenDroneMap reads it: CRS line, then ``x y z px py image name``."""

    t = transformer(gcps.crs, crs)
    by_name = gcps.by_name()
    lines = [crs_to_text(crs)]
    geographic = crs.is_geographic
    for o in sorted((o for o in observations if o.status == DETECTED), key=lambda o: (o.gcp, o.image)):
        g = by_name[o.gcp]
        x, y = t.transform(g.x, g.y)
        fmt = "{:.9f} {:.9f}" if geographic else "{:.4f} {:.4f}"
        lines.append(f"{fmt.format(x, y)} {g.z:.4f} {o.x_px:.3f} {o.y_px:.3f} {o.image} {o.gcp}")
    return write_text(path, "\n".join(lines) + "\n")


def write_detections(path: Path, observations: list[Observation], gcps: GcpSet) -> Path:
    """Every candidate as a table: GeoPackage (points at the GCP) or CSV, by extension."""
    import geopandas as gpd
    import shapely

    by_name = gcps.by_name()
    rows: list[dict[str, Any]] = []
    for o in observations:
        r = {k: getattr(o, k) for k in Observation.__dataclass_fields__ if k != "corners_px"}
        r["corners_px"] = ";".join(f"{x:.3f} {y:.3f}" for x, y in o.corners_px)
        rows.append(r)
    path = Path(path)
    if path.suffix.lower() == ".csv":
        import csv
        import io

        buf = io.StringIO()
        wr = csv.DictWriter(buf, fieldnames=list(rows[0]) if rows else ["image"])
        wr.writeheader()
        wr.writerows(rows)
        return write_text(path, buf.getvalue())
    geoms = [shapely.Point(by_name[o.gcp].x, by_name[o.gcp].y) if o.gcp in by_name else None for o in observations]
    gdf = gpd.GeoDataFrame(rows, geometry=geoms, crs=gcps.crs)
    return write_vector(path, {"detections": gdf}, styles=product_styles("detections"))


def write_review(
    path: Path, observations: list[Observation], paths: dict[str, Path], crop_px: int = 128, columns: int = 8
) -> Path:
    """PNG contact sheet: a crop around each detection, centre marked, labelled GCP / image; model
    fits are marked (V verified on blue, F fitted on orange, a yellow centre), decoded ones plain."""
    import cv2

    accepted = [o for o in observations if o.status == DETECTED]
    tiles = []
    cache: dict[str, np.ndarray] = {}
    half = crop_px // 2
    for o in sorted(accepted, key=lambda o: (o.gcp, o.image)):
        img = cache.get(o.image)
        if img is None:
            cache.clear()  # one photo in memory at a time (observations are sorted by GCP)
            read = cv2.imread(str(paths[o.image]), cv2.IMREAD_COLOR)
            if read is None:
                continue  # a photo that cannot be read again is left off the contact sheet
            img = cache[o.image] = read
        # crop scaled so the marker fills about half the tile
        scale = max(1.0, (crop_px * 0.5) / max(o.side_px, 1.0))
        m = np.array([[scale, 0, half - scale * o.x_px], [0, scale, half - scale * o.y_px]])
        tile = cv2.warpAffine(img, m, (crop_px, crop_px + 18), flags=cv2.INTER_LINEAR, borderValue=(40, 40, 40))
        # a person checks verified and fitted detections (model fits, no id decoded) first:
        # their label says so, on a colour of its own
        look = {"verified": ("V ", (160, 60, 0), (0, 255, 255)), "fitted": ("F ", (0, 90, 200), (0, 255, 255))}
        prefix, bar_bgr, mark_bgr = look.get(o.method, ("", (0, 0, 0), (0, 0, 255)))
        cv2.drawMarker(tile, (half, half), mark_bgr, cv2.MARKER_CROSS, 14, 1)
        label = f"{prefix}{o.gcp} {Path(o.image).stem}"[:22]
        cv2.rectangle(tile, (0, crop_px), (crop_px, crop_px + 18), bar_bgr, -1)
        cv2.putText(tile, label, (2, crop_px + 13), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    if not tiles:
        tiles = [np.zeros((crop_px + 18, crop_px, 3), np.uint8)]
    rows = [tiles[i : i + columns] for i in range(0, len(tiles), columns)]
    blank = np.zeros_like(tiles[0])
    sheet = np.vstack([np.hstack(r + [blank] * (columns - len(r))) for r in rows])
    return write_png(path, sheet)
