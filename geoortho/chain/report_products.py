"""The report's product sections: the DSM and DTM (hillshades, terrain figures), the orthophoto and the
photos it is drawn from, its seams.
"""

from __future__ import annotations

import html
import math
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.chain.quality import as_number
from geoortho.chain.report_base import (
    MAX_RASTER_PX,
    ReportContext,
    cell_size_text,
    crs_label,
    furnish,
    html_table,
    key_values,
    missing_note,
    new_figure,
    png_file,
    png_img,
    read_raster,
    unit_symbol,
)


def elevation_section(ctx: ReportContext) -> str:
    d = ctx.done("dem")
    if d is None:
        return missing_note("The dem stage did not finish.")
    from matplotlib.colors import LightSource, Normalize

    parts = []
    fig = new_figure(7.5, 3.8)
    for i, (label, key) in enumerate((("DSM", "dsm"), ("DTM", "dtm"))):
        path = ctx.path("dem", key)
        if path is None:
            continue
        data, valid, extent, unit = read_raster(path, [1])
        z = np.where(valid, data[0], np.nan).astype(float)
        ax = fig.add_subplot(1, 2, i + 1)
        if not np.isfinite(z).any():
            ax.set_title(f"{label}: no data")
            continue
        lo, hi = np.nanpercentile(z, [1, 99])
        norm = Normalize(lo, hi if hi > lo else lo + 1)
        cell = (extent[1] - extent[0]) / z.shape[1]
        filled = np.where(np.isfinite(z), z, lo)
        import matplotlib

        cmap = matplotlib.colormaps["terrain"]
        rgb = LightSource(azdeg=315, altdeg=45).shade(
            filled, cmap=cmap, norm=norm, blend_mode="soft", vert_exag=1.0, dx=cell, dy=cell
        )
        rgb[..., 3] = np.isfinite(z)
        ax.imshow(rgb, extent=extent, interpolation="bilinear")
        sm = matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap)
        cbar = fig.colorbar(sm, ax=ax, shrink=0.75)
        cbar.set_label(f"elevation ({unit or 'CRS units'})")
        ax.set_title(label, fontsize=10)
        ax.set_aspect("equal")
        furnish(ax, crs_label(ctx), unit_symbol(unit))
    parts.append(png_img(fig, "DSM and DTM hillshades"))
    dense = ctx.dense_report()
    pairs: list[tuple[str, Any]] = [
        ("Point cloud", "lidar (given)" if "dense" not in ctx.stages else "dense, from the photos"),
        ("Points / ground points", f"{d.get('n_points'):,} / {d.get('n_ground'):,}"),
        ("Cell size", cell_size_text(d)),
    ]
    if dense:
        pairs += [
            ("Depth maps", f"{dense.get('depth_maps')} of {dense.get('photos')} photos ({dense.get('pairs')} pairs)"),
            (
                "Dense points matched / consistent / written",
                " / ".join(f"{dense.get(k):,}" for k in ("points_matched", "points_consistent", "points_written")),
            ),
        ]
    pairs += _terrain_pairs(d)
    parts.append(key_values(pairs))
    return "".join(parts)


def _terrain_pairs(d: dict[str, Any]) -> list[tuple[str, Any]]:
    """What the DTM is made of and what its hillshade would show, as dem measured it."""

    def num(key: str) -> float:
        return as_number(d.get(key))

    pairs: list[tuple[str, Any]] = []
    measured, under = num("dtm_measured_share"), num("dtm_under_object_share")
    if math.isfinite(measured):
        seen = num("seen_m2")
        area = f" ({under * seen:,.0f} m²)" if math.isfinite(seen) and math.isfinite(under) else ""
        pairs.append(
            (
                "DTM: ground measured / under objects, no ground seen",
                f"{measured:.1%} / {under:.1%}{area} (dtm_source.tif: 1 measured, 2 interpolated, 4 no ground seen)",
            )
        )
    rough, step = num("dtm_roughness_m"), num("footprint_step_m")
    if math.isfinite(rough) or math.isfinite(step):
        pairs.append(
            (
                "DTM roughness on open ground / step at footprint edges",
                f"{100 * rough:.1f} cm / {100 * step:.1f} cm RMS",
            )
        )
    interval = num("contour_interval_m")
    if math.isfinite(interval) and d.get("contours"):
        pairs.append(("Contours", f"every {interval:g} m ({Path(str(d.get('contours'))).name})"))
    return pairs


def ortho_section(ctx: ReportContext) -> str:
    o = ctx.ortho_report()
    path = ctx.path("ortho", "preview")
    if o is None:
        return missing_note("The ortho stage did not finish.")
    parts = [png_file(path, "orthophoto preview")] if path is not None else []
    covered = float(o.get("coverage_px") or 0)
    holes = float(o.get("holes_left_px") or 0)
    parts.append(
        key_values(
            [
                ("Size", f"{o.get('width_px')} × {o.get('height_px')} px at {100 * float(o['resolution_m']):.2f} cm"),
                ("Photos used", f"{o.get('n_used')} of {o.get('n_photos')}"),
                ("Poses", o.get("poses")),
                ("Surface", o.get("surface")),
                (
                    "Holes filled / left (pixels)",
                    f"{o.get('holes_filled_px'):,} / {int(holes):,}"
                    + (f" ({100 * holes / (covered + holes):.1f} % of the extent)" if covered + holes else ""),
                ),
                *_ortho_sources(o),
            ]
        )
    )
    parts.append(_ortho_sources_map(ctx, o))
    return "".join(parts)


def mesh_section(ctx: ReportContext) -> str:
    """The 3D mesh: an oblique picture, its size and its error against the DSM it was made from."""
    m = ctx.done("mesh")
    if m is None:
        return missing_note("The mesh stage did not finish.")
    view = ctx.path("mesh", "view")
    parts = [png_file(view, "the textured mesh seen from the south-west")] if view is not None else []

    def num(key: str) -> float:
        v = m.get(key)
        return float(v) if isinstance(v, (int, float)) else math.nan

    tiles = f"{int(num('n_tiles'))} tiles in {int(num('n_levels'))} levels of detail" if m.get("tileset") else "none"
    parts.append(
        key_values(
            [
                (
                    "Faces",
                    f"{int(num('n_faces')):,} ({num('faces_per_ha'):,.0f} a hectare; "
                    f"{num('mb_per_ha'):.2f} MB a hectare as glTF)",
                ),  # fmt: skip
                (
                    "Heights against the DSM",
                    f"RMSE {100 * num('rmse_m'):.1f} cm (asked: at most "
                    f"{100 * num('max_rmse_m'):.1f} cm a tile); largest {num('max_error_m'):.2f} m, at a wall",
                ),  # fmt: skip
                ("Texture", f"the orthophoto at {100 * num('texture_cell_m'):.1f} cm a pixel"),
                ("Walls", _walls_text(num("wall_faces"), num("wall_photo_share"))),
                ("Files", f"{Path(str(m.get('output'))).name} (glTF), 3D Tiles: {tiles}"),
            ]
        )
    )
    return "".join(parts)


def _walls_text(faces: float, photo_share: float) -> str:
    """What coloured the mesh's walls (faces steeper than 60 degrees, which the orthophoto sees edge-on)."""
    if not math.isfinite(faces) or faces <= 0:
        return "the orthophoto's colours at their tops and feet (no walls on their own atlas)"
    if not math.isfinite(photo_share):
        return f"{int(faces):,} faces on their own atlas"
    return (
        f"{int(faces):,} faces on their own atlas, {100 * photo_share:.0f} % of their area coloured from the photo "
        "that sees it most directly; the rest, which no photo sees, from the orthophoto"
    )


def volumes_section(ctx: ReportContext) -> str | None:
    """The volumes over the polygons given: per polygon, cut, fill, net and its uncertainty, and what
    of it stands on interpolated cells or off the surface."""
    v = ctx.done("volume")
    if v is None:
        return None if "volume" not in ctx.stages else missing_note("The volume stage did not finish.")
    path = ctx.path("volume", "output")
    if path is None:
        return missing_note("The volumes' GeoPackage is missing.")
    import geopandas as gpd

    table = gpd.read_file(path, layer="volumes")

    def m3(x: Any) -> str:
        return f"{float(x):,.1f}" if x is not None and math.isfinite(float(x)) else "–"

    def share(x: Any) -> str:
        return f"{100 * float(x):.1f} %" if x is not None and math.isfinite(float(x)) else "not known"

    rows = [[r["name"], r["base_method"], f"{float(r['area_m2']):,.0f}", m3(r["cut_m3"]), m3(r["fill_m3"]),
             f"{m3(r['net_m3'])} ± {m3(r['sigma_m3'])}", share(r["interpolated_share"]), share(r["uncovered_share"]),
             r["note"] or ""] for _, r in table.iterrows()]  # fmt: skip
    head = ["polygon", "base", "area m²", "cut m³", "fill m³", "net m³ (± 1σ)", "on interpolated cells",
            "without surface", "note"]  # fmt: skip
    said = html.escape(str(v.get("accuracy_source") or ""))
    return html_table(head, rows) + (
        f"<p>Cut: above the base; fill: below it. The uncertainty: {said}; a shift of the whole survey "
        "counts over a fixed base only (a base drawn from the surface moves with it), the noise by "
        "1 m patches, the base's own noise by its edge's patches.</p>"
    )


#: The change section lists at most this many areas, the largest volumes first.
CHANGE_ROWS = 12


def change_section(ctx: ReportContext) -> str | None:
    """What changed since the earlier survey: the fit that brought it onto this one, the difference
    map with the cut and fill areas outlined, and the areas' volumes."""
    c = ctx.done("change")
    if c is None:
        return None if "change" not in ctx.stages else missing_note("The change stage did not finish.")
    diff_path, poly_path = ctx.path("change", "output"), ctx.path("change", "polygons")
    if diff_path is None or poly_path is None:
        return missing_note("The change products are missing.")
    import geopandas as gpd
    import matplotlib
    from matplotlib.colors import LinearSegmentedColormap, Normalize

    from geoortho.core.styles import DIVERGING

    areas = gpd.read_file(poly_path, layer="change")
    data, valid, extent, unit = read_raster(diff_path, [1])
    d = np.where(valid, data[0], np.nan).astype(float)
    m = float(np.nanpercentile(np.abs(d), 98)) if np.isfinite(d).any() else 1.0
    m = max(m, 2 * as_number(c.get("lod_m")) if math.isfinite(as_number(c.get("lod_m"))) else m, 0.01)
    fig = new_figure(7.0, 5.0)
    ax = fig.add_subplot()
    cmap = LinearSegmentedColormap.from_list("change", list(DIVERGING))
    norm = Normalize(-m, m)
    ax.imshow(np.ma.masked_invalid(d), extent=extent, cmap=cmap, norm=norm, interpolation="nearest")
    for kind, colour in (("cut", DIVERGING[0]), ("fill", DIVERGING[-1])):
        part = areas[areas["kind"] == kind]
        if len(part):
            part.boundary.plot(ax=ax, color=colour, linewidth=1.0)
    cbar = fig.colorbar(matplotlib.cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.8)
    cbar.set_label("this survey minus the earlier (m)")
    ax.set_aspect("equal")
    furnish(ax, crs_label(ctx), unit_symbol(unit))
    reference = Path(str(ctx.values("change").get("reference") or ""))
    project = reference.parent.parent if reference.parent.name == "dem" else reference.parent

    def num(k: str, scale: float = 1.0, digits: int = 2) -> str:
        v = as_number(c.get(k))
        return f"{v * scale:,.{digits}f}" if math.isfinite(v) else "–"

    pairs: list[tuple[str, Any]] = [
        ("Earlier survey", f"{project.name} ({reference})"),
        (
            "Brought onto this one by",
            f"{num('shift_x_m')} m east, {num('shift_y_m')} m north, {num('shift_z_m')} m up; turned "
            f"{num('rotation_deg', digits=3)}°, tilt {num('tilt_deg', digits=3)}° taken out",
        ),
        (
            "On the ground that did not change",
            f"{num('stable_share', 100, 0)} % of the common ground; residual {num('residual_m', 100, 1)} cm (NMAD)",
        ),  # fmt: skip
        (
            "Level of detection (95 %, flat ground)",
            f"{num('lod_m', 100, 1)} cm a cell, more on slopes; "
            f"{num('area_lod_m', 100, 1)} cm of an area's mean (how far a metre's patch strays where nothing "
            "changed)",
        ),  # fmt: skip
        ("Left out: on interpolated surface", f"{c.get('n_interpolated', 0)} area(s)"),
        (
            "Cut (removed) / fill (added)",
            f"{num('cut_m3', digits=1)} m³ in {c.get('n_cut')} areas / "
            f"{num('fill_m3', digits=1)} m³ in {c.get('n_fill')} areas",
        ),  # fmt: skip
    ]
    rows = []
    if len(areas):
        top = areas.assign(size=areas["volume_m3"].abs()).sort_values("size", ascending=False).head(CHANGE_ROWS)
        rows = [
            [r["kind"], f"{float(r['area_m2']):,.1f}", f"{float(r['volume_m3']):+,.1f} ± {float(r['sigma_m3']):,.1f}"]
            for _, r in top.iterrows()
        ]
    table = (
        html_table(["area", "m²", "volume m³ (± 1σ)"], rows)
        if rows
        else "<p>No change beyond the level of detection.</p>"
    )
    more = f"<p>The {CHANGE_ROWS} largest of {len(areas)} areas.</p>" if len(areas) > CHANGE_ROWS else ""
    return png_img(fig, "change since the earlier survey") + key_values(pairs) + table + more


def _ortho_sources_map(ctx: ReportContext, o: dict[str, Any]) -> str:
    """The orthophoto, greyed, with what was not plainly seen on a measured surface over it: the
    DSM interpolated (its source raster), ground seen by no photo, inpainted pixels."""
    src = Path(str(o.get("source") or ""))
    if not src.is_file():
        return ""
    import rasterio
    from matplotlib.patches import Patch
    from rasterio.enums import Resampling

    from geoortho.elevation.coverage import MEASURED
    from geoortho.orthophoto.provenance import INPAINTED, OCCLUDED

    with rasterio.open(src) as ds:
        scale = max(1.0, max(ds.width, ds.height) / MAX_RASTER_PX)
        shape = (max(1, round(ds.height / scale)), max(1, round(ds.width / scale)))
        how = ds.read(2, out_shape=shape, resampling=Resampling.nearest)
        b = ds.bounds
    extent = (b.left, b.right, b.bottom, b.top)
    fig = new_figure(7.0, 4.8)
    ax = fig.add_subplot()
    path = ctx.path("ortho", "output")
    if path is not None:
        data, valid, o_extent, _ = read_raster(path, [1, 2, 3])
        grey = data.astype(float).mean(axis=0) / 255.0
        ax.imshow(np.dstack([grey, grey, grey, valid * 0.6]), extent=o_extent, interpolation="bilinear")
    legend = []

    def tint(
        mask: np.ndarray, rgb: tuple[float, float, float], alpha: float, where: tuple[float, ...], label: str
    ) -> None:
        if mask.any():
            ax.imshow(np.dstack([*(np.full(mask.shape, c) for c in rgb), mask * alpha]), extent=where,
                      interpolation="nearest")  # fmt: skip
        legend.append(Patch(color=(*rgb, max(alpha, 0.5)), label=label))

    dsm_source = ctx.path("dem", "dsm_source")
    if dsm_source is not None:
        d, d_valid, d_extent, _ = read_raster(dsm_source, [1])
        tint(d_valid & (np.rint(d[0]) != MEASURED), (0.0, 0.35, 1.0), 0.35, d_extent, "on an interpolated DSM")
    tint(how == OCCLUDED, (0.9, 0.0, 0.9), 1.0, extent, "seen by no photo (occluded)")
    tint(how == INPAINTED, (1.0, 0.1, 0.0), 1.0, extent, "inpainted")
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.legend(handles=legend, fontsize=8, loc="lower right")
    furnish(ax, crs_label(ctx))
    ax.set_title("Where the orthophoto is not plainly seen on a measured surface", fontsize=10)
    return png_img(fig, "orthophoto sources map")


def _ortho_sources(o: dict[str, Any]) -> list[tuple[str, Any]]:
    """Where the orthophoto's pixels came from: on a surface measured or not, seen or occluded."""
    area = as_number(o.get("area_m2"))
    if not math.isfinite(area) or area <= 0:
        return []

    def share(key: str) -> str:
        v = as_number(o.get(key))
        return f"{v:,.1f} m² ({100 * v / area:.2f} %)" if math.isfinite(v) else "–"

    rows: list[tuple[str, Any]] = [
        ("On an interpolated DSM", share("on_interpolated_m2")),
        ("Seen by no photo (occluded: from the nearest view)", share("occluded_m2")),
        (
            "Holes inside the orthophoto",
            f"{share('holes_inside_m2')}, {as_number(o.get('holes_inside_n')):.0f} holes"
            if as_number(o.get("holes_inside_n")) > 0
            else "none",
        ),
    ]
    src, seams = o.get("source"), o.get("seamlines")
    if src or seams:
        rows.append(("Each pixel's photo", " and ".join(Path(str(p)).name for p in (src, seams) if p)))
    return rows


def seams_section(ctx: ReportContext) -> str:
    o = ctx.ortho_report()
    if o is None:
        return missing_note("The ortho stage did not finish.")
    gains = o.get("gains_bgr") or {}
    parts = [
        key_values(
            [
                (
                    "Colour step across seams, before / after balancing",
                    " / ".join(f"{o.get(k, float('nan')):.1f}" for k in ("seam_mismatch_raw", "seam_mismatch_balanced"))
                    + " DN",
                ),
                (
                    "Step across seams vs within a photo (texture)",
                    f"{o.get('seam_step_dn', float('nan')):.1f} / {o.get('texture_step_dn', float('nan')):.1f} DN",
                ),
                ("Seam pixels", o.get("seam_pixels")),
            ]
        )
    ]
    if gains:
        names = list(gains)
        g = np.array([gains[n] for n in names], dtype=float)  # B, G, R
        fig = new_figure(7.5, 3.2)
        ax = fig.add_subplot()
        x = np.arange(len(names))
        for k, (colour, label) in enumerate((("#1f77b4", "blue"), ("#2ca02c", "green"), ("#d62728", "red"))):
            ax.plot(x, g[:, k], marker=".", lw=0.8, color=colour, label=label)
        ax.axhline(1.0, color="k", lw=0.6)
        ax.set_ylabel("gain")
        ax.set_xlabel("photo")
        if len(names) <= 40:
            ax.set_xticks(x, names, rotation=90, fontsize=6)
        ax.legend(fontsize=8, ncols=3)
        parts.append(png_img(fig, "colour balance gain per photo"))
        far = [n for n, v in zip(names, g) if np.max(np.abs(np.log(np.clip(v, 1e-3, None)))) > math.log(1.25)]
        if far:
            parts.append(
                f'<p class="warn">Gains beyond ±25 % (exposure steps?): {html.escape(", ".join(far[:20]))}</p>'
            )
    return "".join(parts)
