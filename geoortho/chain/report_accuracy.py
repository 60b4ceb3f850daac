"""The report's accuracy sections: the photos' positions and their fixes, the GCPs and checkpoints with
their residuals (drawn, and written as layers for QGIS), the reprojection error, the photos not used.
"""

from __future__ import annotations

import html
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.chain.report_base import (
    ReportContext,
    as_cm,
    crs_label,
    furnish,
    html_table,
    key_values,
    map_figure,
    missing_note,
    new_figure,
    ortho_background,
    png_img,
)
from geoortho.core.colmap import load_pycolmap
from geoortho.core.crs import transformer
from geoortho.core.outputs import write_vector
from geoortho.core.styles import product_styles
from geoortho.gcp.io import read_gcp_file
from geoortho.photos.metadata import list_images

#: How each position accuracy class is drawn on the map.
_FIX_STYLE = {
    "fixed": ("#1a7f37", "RTK fixed"),
    "float": ("#e6a100", "RTK float"),
    "single": ("#b00020", "single point (fix lost)"),
    "stated": ("#1f77b4", "accuracy stated"),
    "consumer": ("#999999", "consumer GPS"),
}


def position_accuracy_section(ctx: ReportContext) -> str:
    """Each photo's position accuracy class on a map, and per class the accuracy stated against
    what the bundle adjustment measured; a positions file and the time lag found in it."""
    sfm = ctx.sfm_report()
    acc = (sfm or {}).get("gps_accuracy")
    if not acc:
        return missing_note(
            "No photo states its position accuracy (consumer GPS): every position is weighed at the "
            "SfM's gps_sigma_m, and the GCPs (if any) carry the georeference."
        )
    parts: list[str] = []
    cams = sfm_cameras(ctx)
    if cams is not None and "gps_fix" in cams:
        fig = map_figure(tuple(cams.total_bounds[[0, 2, 1, 3]]), width_in=6.5)
        ax = fig.add_subplot()
        ortho_background(ax, ctx)
        for fix, (colour, label) in _FIX_STYLE.items():
            sel = cams["gps_fix"] == fix
            if sel.any():
                ax.scatter(
                    cams.geometry.x[sel], cams.geometry.y[sel], s=22, c=colour, edgecolor="k", lw=0.3,
                    label=f"{label} ({int(sel.sum())})", zorder=4,
                )  # fmt: skip
        ax.set_aspect("equal")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
        furnish(ax, crs_label(ctx))
        parts.append(png_img(fig, "camera positions by accuracy class"))
    rows = []
    for fix, c in sorted(acc["classes"].items(), key=lambda kv: -kv[1]["photos"]):
        agrees = c.get("rmse_h_m") is not None and c["rmse_h_m"] <= 2.0 * c["sigma_h_m"]
        rows.append(
            [
                _FIX_STYLE.get(fix, ("", fix))[1],
                c["photos"],
                as_cm(c["sigma_h_m"]),
                as_cm(c["sigma_v_m"]),
                as_cm(c.get("rmse_h_m")),
                as_cm(c.get("rmse_v_m")),
                '<span class="ok">agrees</span>' if agrees else '<span class="warn">off its stated accuracy</span>',
            ]
        )
    if acc.get("consumer"):
        rows.append([_FIX_STYLE["consumer"][1], acc["consumer"], "–", "–", "–", "–", "weighed at gps_sigma_m"])
    parts.append(
        html_table(
            ["class", "photos", "stated σ H", "stated σ V", "measured RMSE H (per axis)", "measured RMSE V", ""],
            rows,
        )
    )
    off = acc.get("off_stated_accuracy") or []
    if off:
        parts.append(
            '<p class="warn">Off their stated accuracy: '
            + html.escape(", ".join(f"{o['image']} ({o['fix']}, {o['dh_m']:.2f} m)" for o in off[:12]))
            + ("…" if len(off) > 12 else "")
            + "</p>"
        )
    pos = (sfm or {}).get("positions")
    if pos:
        lag = pos.get("time_lag") or {}
        pairs = [
            ("Positions file", f"{html.escape(Path(pos['file']).name)} ({html.escape(pos['format'])}), "
             f"{pos['photos']} photos"),
        ]  # fmt: skip
        if pos.get("time_offset_s") is not None:
            how = "found from the photos' own GPS" if pos.get("time_offset_found") else "as given"
            pairs.append(("Time offset (file − camera clock)", f"{pos['time_offset_s']:+.3f} s ({how})"))
        if lag:
            pairs.append(("Camera-to-GPS time lag", f"{lag['lag_s']:+.3f} s (± {lag['sigma_s']:.3f} s)"))
        if pos.get("photos_without"):
            pairs.append(("Photos without a position in it", ", ".join(pos["photos_without"][:10])))
        parts.append(key_values(pairs))
    return "".join(parts)


def sfm_cameras(ctx: ReportContext) -> Any:
    path = ctx.path("sfm", "cameras")
    if path is None:
        return None
    import geopandas as gpd

    return gpd.read_file(path, layer="cameras")


def gcp_positions(ctx: ReportContext) -> list[tuple[str, float, float, float]]:
    """(name, x, y, z) of the GCPs in the found gcp_list.txt (the CRS of the products)."""
    used = ctx.values("sfm").get("gcp_list")  # found by gcp-find, or given as observations
    path = Path(used) if isinstance(used, str) and Path(used).is_file() else None
    if path is None:
        return []
    from pyproj import CRS

    gcps = read_gcp_file(path)
    points = list(gcps.by_name().items())
    # the products' CRS, whatever CRS the GCP list is in (EPSG:4326 lon/lat drew at (0, 0) of UTM axes)
    target = crs_label(ctx)
    if not points or not target:
        return [(n, g.x, g.y, g.z) for n, g in points]
    to = transformer(gcps.crs, CRS.from_user_input(target))
    xs, ys = to.transform(np.array([g.x for _, g in points]), np.array([g.y for _, g in points]))
    return [(n, float(x), float(y), g.z) for (n, g), x, y in zip(points, xs, ys)]


#: Where the report writes the GCPs and their residual vectors as layers, for the QGIS project.
RESIDUALS_NAME = "gcp_residuals.gpkg"


@dataclass(frozen=True)
class _Residuals:
    """The SfM report's GCP residuals that have a surveyed place, as the report's plot and the QGIS
    project's layer both draw them."""

    records: list[dict[str, Any]]
    xy: np.ndarray  # (n, 2) their surveyed places, in the products' CRS
    d: np.ndarray  # (n, 2) their horizontal residuals (m)
    span_m: float  # the GCPs' spread
    longest_m: float  # the longest horizontal residual

    @property
    def scale(self) -> float:
        """The arrows' exaggeration: the longest is 12 % of the GCPs' spread."""
        return 0.12 * self.span_m / self.longest_m


def _residuals(ctx: ReportContext, sfm: dict[str, Any]) -> _Residuals:
    where = {n: (x, y) for n, x, y, _ in gcp_positions(ctx)}
    res = [r for r in sfm.get("gcps", []) if r.get("name") in where and r.get("dx_m") is not None]
    xy = np.array([where[r["name"]] for r in res], float).reshape(-1, 2)
    d = np.array([[r["dx_m"], r["dy_m"]] for r in res], float).reshape(-1, 2)
    span = max(float(np.ptp(xy[:, 0])), float(np.ptp(xy[:, 1])), 1.0) if res else 1.0
    longest = max(float(np.nanmax(np.hypot(d[:, 0], d[:, 1]))), 1e-6) if res else 1e-6
    return _Residuals(res, xy, d, span, longest)


def write_residual_layers(ctx: ReportContext, project: Path) -> Path | None:
    """The GCPs and checkpoints at their surveyed places with their residuals (``gcps``), and each
    horizontal residual as a line drawn ``exaggeration`` times its length (``residuals``), as the
    report's plot draws them."""
    found = _residuals(ctx, ctx.sfm_report() or {})
    res, xy, d = found.records, found.xy, found.d
    crs = crs_label(ctx)
    target = project / RESIDUALS_NAME
    if not res or not crs:
        target.unlink(missing_ok=True)
        return None
    import geopandas as gpd
    import shapely

    fields = {
        "name": [r["name"] for r in res],
        "role": [r.get("role", "") for r in res],
        "dx_m": d[:, 0],
        "dy_m": d[:, 1],
        "dz_m": [r.get("dz_m") for r in res],
        "horizontal_m": np.hypot(d[:, 0], d[:, 1]),
        "photos": [r.get("observations") for r in res],
    }
    points = gpd.GeoDataFrame(fields, geometry=shapely.points(xy), crs=crs)
    lines = gpd.GeoDataFrame(
        {**fields, "exaggeration": np.full(len(res), round(found.scale, 1))},
        geometry=shapely.linestrings(np.stack([xy, xy + d * found.scale], axis=1)),
        crs=crs,
    )
    write_vector(target, {"gcps": points, "residuals": lines}, styles=product_styles("gcps", "residuals"))
    return target


def _accuracy_rows(sfm: dict[str, Any]) -> list[list[Any]]:
    rows = []
    for label, key in (("GCPs (control)", "gcp_accuracy"), ("Checkpoints", "checkpoint_accuracy")):
        a = sfm.get(key)
        if not a:
            continue
        rows.append(
            [
                label,
                a.get("n"),
                as_cm(a.get("rmse_x_m")),
                as_cm(a.get("rmse_y_m")),
                as_cm(a.get("rmse_horizontal_m")),
                as_cm(a.get("rmse_z_m")),
                as_cm(a.get("rmse_3d_m")),
                as_cm(a.get("ce90_m")),
                as_cm(a.get("le90_m")),
            ]
        )
    return rows


def gcps_section(ctx: ReportContext) -> str:
    given = "gcp-find" in ctx.stages or bool(ctx.values("sfm").get("gcp_list"))
    sfm = ctx.sfm_report()
    parts: list[str] = []
    g = ctx.done("gcp-find")
    if "gcp-find" not in ctx.stages and given:
        parts.append(f"<p>GCP observations given: {html.escape(str(ctx.values('sfm')['gcp_list']))}</p>")
    if not given:
        return missing_note(
            "No GCP file was given: the products' absolute accuracy is the photos' GPS "
            + (f"(SfM: {sfm.get('georeferenced_by')})." if sfm else ".")
        )
    if g is not None:
        parts.append(
            key_values(
                [
                    ("GCPs found in the photos", g.get("n_gcps_found")),
                    ("Marker observations written (gcp_list.txt)", g.get("n_observations")),
                    ("Photo/GCP candidates searched", g.get("n_candidates")),
                ]
            )
        )
        if not g.get("n_observations"):
            parts.append('<p class="bad">No GCP marker was found in any photo: SfM ran without GCPs.</p>')
    if not sfm or not sfm.get("gcps"):
        return "".join(parts) or missing_note("SfM did not finish.")
    rows = [
        [
            r.get("name"),
            r.get("role"),
            r.get("observations"),
            r.get("inliers"),
            as_cm(r.get("dx_m")),
            as_cm(r.get("dy_m")),
            as_cm(r.get("dz_m")),
            None if r.get("reprojection_px") is None else f"{r['reprojection_px']:.2f}",
        ]
        for r in sfm["gcps"]
    ]
    parts.append(
        "<h3>Residuals per point</h3><p>Measured minus surveyed, in the products' CRS.</p>"
        + html_table(["name", "role", "photos", "inliers", "dX", "dY", "dZ", "reprojection (px)"], rows)
    )
    acc = _accuracy_rows(sfm)
    if acc:
        parts.append(
            "<h3>Accuracy</h3>"
            + html_table(["", "n", "RMSE X", "RMSE Y", "RMSE XY", "RMSE Z", "RMSE 3D", "CE90", "LE90"], acc)
            + f'<p class="muted">{html.escape(str(sfm.get("ce90_le90", "")))}</p>'
        )
    parts.append(_residual_plot(ctx, sfm))
    return "".join(parts)


def _residual_plot(ctx: ReportContext, sfm: dict[str, Any]) -> str:
    found = _residuals(ctx, sfm)
    res, scale, span, longest = found.records, found.scale, found.span_m, found.longest_m
    if not res:
        return ""
    (xs, ys), (dx, dy) = found.xy.T, found.d.T
    dz = np.array([r["dz_m"] if r.get("dz_m") is not None else np.nan for r in res], dtype=float)
    fig = new_figure(7.0, 5.5)
    ax = fig.add_subplot()
    ortho_background(ax, ctx)
    control = np.array([r.get("role") == "control" for r in res])
    lim = max(float(np.nanmax(np.abs(dz))) if np.isfinite(dz).any() else 0.01, 0.01)
    sc = ax.scatter(
        xs,
        ys,
        c=dz,
        cmap="coolwarm",
        vmin=-lim,
        vmax=lim,
        s=np.where(control, 60, 90),
        marker="o",
        edgecolor="k",
        zorder=4,
    )
    for is_control, colour, label in ((True, "#1f3a93", "control"), (False, "#c0392b", "checkpoint")):
        sel = control == is_control
        if sel.any():
            ax.quiver(
                xs[sel],
                ys[sel],
                dx[sel] * scale,
                dy[sel] * scale,
                angles="xy",
                scale_units="xy",
                scale=1,
                color=colour,
                width=0.004,
                zorder=5,
                label=f"{label} (horizontal residual)",
            )
    for r, x, y in zip(res, xs, ys):
        ax.annotate(r["name"], (x, y), textcoords="offset points", xytext=(5, 5), fontsize=7, zorder=6)
    if np.isfinite(dz).any():
        cbar = fig.colorbar(sc, ax=ax, shrink=0.8)
        cbar.set_label("vertical residual dZ (m)")
    else:  # heights not controlled: grey dots, no colour bar pretending a dZ of 0
        sc.set_facecolor("#bbbbbb")
    ax.set_title(f"arrows ×{scale:.3g}: the longest is {100 * longest:.1f} cm", fontsize=9)
    ax.set_aspect("equal")
    pad = 0.1 * span
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(ys.min() - pad, ys.max() + pad)
    ax.legend(loc="lower right", fontsize=8)
    furnish(ax, crs_label(ctx))
    return "<h3>Residual vectors</h3>" + png_img(fig, "GCP and checkpoint residual vectors")


def reprojection_section(ctx: ReportContext) -> str:
    model = ctx.path("sfm", "model")
    sfm = ctx.sfm_report()
    if model is None or sfm is None:
        return missing_note("SfM did not finish.")

    pycolmap = load_pycolmap()

    rec = pycolmap.Reconstruction(str(model))
    errors = np.array([p.error for p in rec.points3D.values()], dtype=float)
    errors = errors[np.isfinite(errors)]
    if errors.size == 0:
        return missing_note("The model has no tie points.")
    fig = new_figure(7.0, 3.5)
    ax = fig.add_subplot()
    top = float(np.percentile(errors, 99.5))
    ax.hist(np.clip(errors, 0, top), bins=60, color="#4c72b0")
    ax.axvline(float(np.mean(errors)), color="k", ls="--", lw=1, label=f"mean {np.mean(errors):.2f} px")
    ax.set_xlabel(f"mean reprojection error of a tie point (px; the last bin holds all ≥ {top:.2f})")
    ax.set_ylabel("tie points")
    ax.legend(fontsize=8)
    return png_img(fig, "reprojection error histogram") + key_values(
        [
            ("Tie points", f"{errors.size:,}"),
            (
                "Mean / median / 95th percentile",
                f"{errors.mean():.2f} / {np.median(errors):.2f} / {np.percentile(errors, 95):.2f} px",
            ),
            ("Mean track length", sfm.get("mean_track_length")),
            ("Matching / mapper", f"{sfm.get('matching')} / {sfm.get('mapper')}"),
        ]
    )


def not_used_section(ctx: ReportContext) -> str:

    rows: list[list[Any]] = []
    images = ctx.values("footprints").get("images")
    fp = ctx.footprints()
    if images and fp is not None and Path(images).is_dir():
        warnings = ctx.stages.get("footprints", {}).get("warnings", [])
        have = set(fp["image"])
        for p in list_images(Path(images)):
            if p.name not in have:
                why = next((w for w in warnings if p.name in w), "no usable metadata (see the run's warnings)")
                rows.append([p.name, "footprints", why])
    sfm = ctx.sfm_report() or {}
    for name, why in {**sfm.get("skipped", {}), **sfm.get("unregistered", {})}.items():
        rows.append([name, "sfm", why])
    dense = ctx.dense_report() or {}
    for name, why in (dense.get("no_depth_map") or {}).items():
        rows.append([name, "dense", f"no depth map: {why}"])
    ortho = ctx.ortho_report() or {}
    for s in ortho.get("skipped", []):
        rows.append([s.get("image"), "ortho", s.get("reason")])
    for name in ortho.get("not_in_mosaic", []):
        rows.append([name, "ortho", "rectified, but no pixel of it is in the mosaic (other photos' views were chosen)"])
    if not rows:
        # said only when each stage says so: the ortho's own count must agree
        if ortho and ortho.get("n_used") != ortho.get("n_photos"):
            return f"<p>The orthophoto used {ortho.get('n_used')} of its {ortho.get('n_photos')} photos.</p>"
        return "<p>Every photo was used by every stage.</p>"
    return html_table(["photo", "stage", "why"], rows)
