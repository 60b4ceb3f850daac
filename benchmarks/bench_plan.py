"""Benchmark: planning a 10 km² AOI (target: < 5 s on one core), with photos/s of footprint prediction.

A 4 x 2.5 km rectangle near Lisbon, DJI Phantom 4 Pro at 3 cm GSD, 75/65 % overlap, the default
GCPs; flat ground and on a hilly DTM (terrain following). Prints wall time, peak memory, photos
planned per second and the footprints' share of the time.

    python benchmarks/bench_plan.py
"""

from __future__ import annotations

import cProfile
import pstats
import resource
import sys
import tempfile
import time
from pathlib import Path

import geopandas as gpd
import numpy as np
import shapely
from rasterio.transform import from_origin

E0, N0, CRS = 487000.0, 4290000.0, "EPSG:32629"


def _hill_dtm(path: Path) -> None:
    from geoortho.core.outputs import write_cog

    cell = 10.0
    cols, rows = 600, 450
    x = E0 - 1000 + (np.arange(cols) + 0.5) * cell
    y = N0 + 3500 - (np.arange(rows) + 0.5) * cell
    X, Y = np.meshgrid(x, y)
    z = 100 + 80 * np.exp(-(((X - E0 - 2000) / 900) ** 2 + ((Y - N0 - 1250) / 700) ** 2))
    write_cog(
        path, z.astype(np.float32), transform=from_origin(E0 - 1000, N0 + 3500, cell, cell), crs=CRS, nodata=-9999.0
    )


def _again_footprints(plan: Path, dtm: Path | None) -> None:
    """compute_footprints on the plan's own cameras (what plan timed inside itself)."""
    import json

    from geoortho.core.camera import Intrinsics, Pose, PosedCamera, rotation_from_ypr
    from geoortho.core.surface import FlatSurface, read_surface
    from geoortho.photos.footprint import compute_footprints

    photos = gpd.read_file(plan, layer="photos")
    c = json.loads(plan.with_name("summary.json").read_text())["camera"]
    intr = Intrinsics(c["width_px"], c["height_px"], c["focal_px"])
    rots = rotation_from_ypr(photos["grid_heading_deg"].to_numpy(), photos["pitch_deg"].to_numpy(), 0.0)
    cams = [
        PosedCamera(intr, Pose(np.array([p.x, p.y, z]), r)) for p, z, r in zip(photos.geometry, photos["z_m"], rots)
    ]
    surface = read_surface(dtm, photos.crs, extend=True) if dtm else FlatSurface(0.0)
    compute_footprints(cams, surface)


def main() -> None:
    import geoortho
    from geoortho.planning.plan import min_module_px

    work = Path(tempfile.mkdtemp(prefix="bench_plan_"))
    aoi = work / "aoi.geojson"
    gpd.GeoDataFrame(geometry=[shapely.box(E0, N0, E0 + 4000, N0 + 2500)], crs=CRS).to_file(aoi)
    dtm = work / "dtm.tif"
    _hill_dtm(dtm)
    min_module_px("DICT_4X4_50")  # measured once per process (about a second), not part of a plan
    for label, extra in (("flat", {}), ("terrain following on a DTM", {"dtm": dtm, "terrain": "follow"})):
        profiling = "--profile" in sys.argv
        prof = cProfile.Profile()
        t = time.perf_counter()
        if profiling:
            prof.enable()
        r = geoortho.plan(aoi, work / label.split()[0], camera="DJI Phantom 4 Pro", gsd_cm=3.0, **extra)
        prof.disable()
        dt = time.perf_counter() - t
        if not profiling:  # the footprints' share, timed alone: the same cameras again
            t = time.perf_counter()
            _again_footprints(r.plan, extra.get("dtm"))
            foot_alone = time.perf_counter() - t
        st = pstats.Stats(prof) if profiling else None
        foot = (
            sum(v[3] for k, v in st.stats.items() if k[2] == "compute_footprints")  # type: ignore[union-attr]
            if st
            else foot_alone
        )
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        print(
            f"{label}: 10 km², {r.n_photos} photos on {r.n_lines} lines in {dt:.2f} s "
            f"({r.n_photos / dt:,.0f} photos/s; target < 5 s: {'met' if dt < 5 else 'NOT met'}), "
            f"peak {peak:.0f} MB"
        )
        print(f"  footprint prediction: {foot:.2f} s = {r.n_photos / max(foot, 1e-9):,.0f} photos/s")
        if st is not None:
            st.sort_stats("cumulative").print_stats("flightplan|footprint|outputs", 20)


if __name__ == "__main__":
    main()
