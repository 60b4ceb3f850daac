"""The quality report of a ``run`` project: one self-contained HTML file a client can read.

Everything in it is read from the project: ``run.json`` (stages, options, timings, memory,
problems) and each stage's own products and reports, so its numbers are theirs. Figures are
drawn with matplotlib (Agg, no pyplot state) and embedded as PNG data URIs: the file needs no
network and prints to PDF from a browser. A section whose products are missing says so; one
that cannot be drawn says why, in red, instead of taking the report down.
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.chain.pipeline import LEDGER_NAME, REPORT_NAME, STAGES, from_ledger, ledger_problem
from geoortho.chain.qgis_project import write_qgis_project
from geoortho.chain.quality import as_number, assess, verdict
from geoortho.core.colmap import load_pycolmap
from geoortho.core.crs import heights_from_text, heights_label, transformer
from geoortho.core.outputs import write_json, write_text, write_vector
from geoortho.core.styles import product_styles
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback
from geoortho.gcp.io import read_gcp_file
from geoortho.photos.metadata import list_images
from geoortho.processing.registry import refuse_writing_into
from geoortho.version import __version__

__all__ = ["ReportResult", "report"]

_DPI = 110
_MAX_RASTER_PX = 900  # rasters are drawn from their overviews at about this size


@dataclass(frozen=True)
class ReportResult:
    """The report written.

    Attributes
    ----------
    output : Path
        report.html.
    n_sections : int
        Sections in it.
    n_problems : int
        Problems it shows in red (stages failed, GCPs not found, sections that could not be drawn).
    verdict : str
        green, amber or red: the worst item of the quality check (red when a problem is shown).
    quality : Path
        quality.json beside the report: every item's value, thresholds and state, and the verdict.
    """

    output: Path
    n_sections: int
    n_problems: int
    verdict: str = "green"
    quality: Path | None = None


#: The version of quality.json's layout (README, "quality.json"): raised when a field changes meaning
#: or goes; a new field does not raise it.
QUALITY_VERSION = 1


def report(project: Path, output: Path | None = None, *, feedback: Feedback | None = None) -> ReportResult:
    """Write the quality report of a project made by ``run``.

    Parameters
    ----------
    project : Path
        The project folder (holds run.json).
    output : Path
        The HTML file to write (default: report.html in the project).
    """

    fb = as_feedback(feedback)
    project = Path(project)
    ledger_path = project / LEDGER_NAME
    if not ledger_path.is_file():
        raise InputError(f"no {LEDGER_NAME}: not a project made by 'run'", path=project)
    try:
        ledger = json.loads(ledger_path.read_text())
        why = ledger_problem(ledger)
    except (ValueError, UnicodeDecodeError) as e:
        why = f"not JSON ({' '.join(str(e).split())})"
    if why:
        raise InputError(f"not a run ledger this version reads: {why}", path=ledger_path)
    if not ledger.get("stages"):
        raise InputError("no stage of this project has run: nothing to report (run it first)", path=ledger_path)
    out = Path(output) if output is not None else project / REPORT_NAME
    _refuse_project_inputs(out, project, ledger)
    ctx = _Context(project, ledger)
    _grade(ctx)
    sections: list[str] = []
    for i, (title, build) in enumerate(_SECTIONS):
        fb.progress(i / len(_SECTIONS))
        try:
            body = build(ctx)
        except Exception as e:  # a section that cannot be drawn is said, the rest still shown
            ctx.problem("report", f"section '{title}' could not be drawn: {type(e).__name__}: {e}")
            body = ""
        if body is not None:
            sections.append(f'<section id="{_anchor(title)}"><h2>{html.escape(title)}</h2>\n{body}\n</section>')
    page = _page(ctx, sections)
    quality = project / "quality.json"
    graded = {"verdict": ctx.verdict, "checks": [asdict(c) for c in ctx.checks], "problems": ctx.problems}
    write_json(quality, {"version": QUALITY_VERSION, **graded})
    write_text(out, page)
    try:  # the products as one styled QGIS project: a convenience, never the report's failure
        _write_residual_layers(ctx, project)
        qgz = write_qgis_project(project)
        if qgz is not None:
            fb.info(f"report: the products as a QGIS project: {qgz}")
    except Exception as e:  # noqa: BLE001
        fb.warning(f"report: no QGIS project written ({type(e).__name__}: {e})")
    level = {"green": fb.info, "amber": fb.warning, "red": fb.warning}[ctx.verdict]
    level(f"report: quality {ctx.verdict.upper()}" + "".join(f"; {c.label}: {c.shown}" for c in _flagged(ctx)))
    fb.progress(1.0)
    return ReportResult(out, len(sections), len(ctx.problems), ctx.verdict, quality)


def _refuse_project_inputs(out: Path, project: Path, ledger: dict[str, Any]) -> None:
    """The report must not overwrite what the project was made from (its photos, GCP files, a
    given DSM) any more than the project's own files (the same check as every command's)."""

    for record in ledger["stages"].values():
        for name, value in from_ledger(record.get("values") or {}, project).items():
            if not isinstance(value, str) or not os.path.isabs(value) or name == "output":
                continue
            given = Path(value)
            if given.is_file() and out.exists() and os.path.samefile(out, given):
                raise ParameterError(
                    "output", f"{out} is the project's input {name}: writing it would destroy it; give another path"
                )
            if given.is_dir():
                refuse_writing_into("output", out, name, given)


def _grade(ctx: _Context) -> None:
    """The quality check of what the stages measured (see geoortho.chain.quality)."""

    try:
        ctx.checks = assess(
            ctx.sfm_report(), ctx.dense_report(), ctx.done("dem"), ctx.ortho_report(), ctx.done("footprints")
        )
    except (TypeError, AttributeError, ValueError, KeyError) as e:  # a hand-edited or damaged stage report
        ctx.problem("report", f"the stage reports hold values of the wrong type ({type(e).__name__}: {e})")
        ctx.checks = assess(None, None, None, None, None)
    ctx.verdict = verdict(ctx.checks, failed=bool(ctx.problems))


def _flagged(ctx: _Context) -> list[Any]:
    return [c for c in ctx.checks if c.state in ("amber", "red")]


def _quality(ctx: _Context) -> str:
    rows = [
        [_Raw(f'<span class="state {c.state.replace(" ", "-")}">{html.escape(c.state)}</span>'), c.label, c.shown,
         c.green, c.red, c.detail]
        for c in ctx.checks
    ]  # fmt: skip
    return (
        '<p class="muted">Each item measured, graded against the thresholds in geoortho.chain.quality '
        "(the README gives each one's reason); the verdict is the worst item's.</p>"
        + _table(["state", "item", "measured", "green", "red", "detail"], rows, "quality")
    )


# --- what the sections read ----------------------------------------------------------------------


class _Context:
    """The project's ledger and products, read once, paths resolved."""

    def __init__(self, project: Path, ledger: dict[str, Any]) -> None:

        self.project = project
        self.ledger = ledger
        self.stages: dict[str, dict[str, Any]] = {
            name: from_ledger(rec, project) for name, rec in ledger.get("stages", {}).items()
        }
        self.problems: list[dict[str, str]] = [dict(p) for p in ledger.get("problems", [])]
        for name, rec in self.stages.items():
            if name != "report" and rec.get("status") in ("failed", "canceled", "running"):
                said = any(p.get("stage") == name and "failed" in p.get("message", "") for p in self.problems)
                if not said:
                    what = {"running": "did not finish (the run was stopped in it)"}.get(rec["status"], rec["status"])
                    self.problems.append(
                        {"stage": name, "level": "error", "message": f"{what}: {rec.get('error', '')}"}
                    )
        self._json: dict[Path, Any] = {}
        self.checks: list[Any] = []
        self.verdict = "green"

    def problem(self, stage: str, message: str) -> None:
        self.problems.append({"stage": stage, "level": "error", "message": message})

    def done(self, stage: str) -> dict[str, Any] | None:
        """The outputs of a stage that finished, or None."""
        rec = self.stages.get(stage)
        return rec.get("outputs") if rec and rec.get("status") == "done" else None

    def path(self, stage: str, key: str) -> Path | None:
        out = self.done(stage)
        v = out.get(key) if out else None
        return Path(v) if isinstance(v, str) and v and Path(v).exists() else None

    def json(self, path: Path | None) -> Any:
        if path is None or not path.is_file():
            return None
        if path not in self._json:
            try:
                self._json[path] = json.loads(path.read_text(encoding="utf-8"))
            except (ValueError, UnicodeDecodeError, RecursionError, OSError) as e:
                # said, and the items it measures are missing (red), not the report's end
                self.problem(
                    "report", f"{path.name} cannot be read as a stage report ({' '.join(str(e).split())[:120]})"
                )
                self._json[path] = None
        return self._json[path]

    def sfm_report(self) -> dict[str, Any] | None:
        r = self.json(self.path("sfm", "report"))
        return r if isinstance(r, dict) else None

    def ortho_report(self) -> dict[str, Any] | None:
        r = self.json(self.path("ortho", "report"))
        return r if isinstance(r, dict) else None

    def dense_report(self) -> dict[str, Any] | None:
        r = self.json(self.path("dense", "report"))
        return r if isinstance(r, dict) else None

    def footprints(self) -> Any:
        path = self.path("footprints", "output")
        if path is None:
            return None
        import geopandas as gpd

        return gpd.read_file(path, layer="footprints")

    def left_out(self) -> Any:
        """The footprints of the photos the SfM left out (from their GPS), or None."""
        path = self.path("footprints", "output")
        if path is None:
            return None
        import geopandas as gpd
        import pyogrio

        if "left_out" not in {str(name) for name, _ in pyogrio.list_layers(path)}:
            return None
        return gpd.read_file(path, layer="left_out")

    def values(self, stage: str) -> dict[str, Any]:
        return dict(self.stages.get(stage, {}).get("values", {}))


# --- drawing helpers -----------------------------------------------------------------------------


def _figure(width_in: float = 7.0, height_in: float = 4.5) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _png(fig: Any, alt: str) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img class="fig" alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _png_file(path: Path, alt: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<img class="fig" alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _read_raster(path: Path, bands: list[int] | None = None) -> tuple[np.ndarray, np.ndarray, tuple[float, ...], Any]:
    """A raster decimated to about _MAX_RASTER_PX (from its overviews): values (bands, rows, cols),
    valid mask, extent (left, right, bottom, top) and its CRS's linear unit name."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(path) as src:
        scale = max(1.0, max(src.width, src.height) / _MAX_RASTER_PX)
        shape = (max(1, round(src.height / scale)), max(1, round(src.width / scale)))
        idx = bands or list(range(1, src.count + 1))
        data = src.read(idx, out_shape=(len(idx), *shape), resampling=Resampling.average, masked=True)
        mask = src.dataset_mask(out_shape=shape, resampling=Resampling.nearest) > 0
        valid = mask & ~np.ma.getmaskarray(data).any(axis=0)
        b = src.bounds
        unit = src.crs.linear_units if src.crs is not None else ""
    return np.ma.getdata(data), valid, (b.left, b.right, b.bottom, b.top), unit


def _ortho_background(ax: Any, ctx: _Context) -> bool:
    """The orthophoto under a map, when there is one."""
    path = ctx.path("ortho", "output")
    if path is None:
        return False
    data, valid, extent, _ = _read_raster(path, [1, 2, 3])
    rgba = np.dstack([np.moveaxis(data, 0, -1).astype(np.uint8), (valid * 255).astype(np.uint8)])
    ax.imshow(rgba, extent=extent, interpolation="bilinear", zorder=0)
    return True


def _table(header: list[str], rows: list[list[Any]], cls: str = "") -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _cell(v: Any) -> str:
    if isinstance(v, _Raw):
        return v.html
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 100 else f"{v:,.0f}"  # never 1.01e+03
    return html.escape(str(v))


@dataclass(frozen=True)
class _Raw:
    html: str


def _kv(pairs: list[tuple[str, Any]]) -> str:
    rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{_cell(v)}</td></tr>" for k, v in pairs)
    return f'<table class="kv">{rows}</table>'


def _cm(v: Any) -> str:
    return "–" if v is None else f"{100 * float(v):.1f} cm"


def _missing(what: str) -> str:
    return f'<p class="muted">{html.escape(what)}</p>'


def _anchor(title: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in title.lower()).strip("-")


# --- the sections --------------------------------------------------------------------------------


def _summary(ctx: _Context) -> str:
    fp = ctx.footprints()
    sfm = ctx.sfm_report() or {}
    pairs: list[tuple[str, Any]] = []
    if fp is not None and len(fp):
        import shapely

        gsd = fp["gsd_cm"].astype(float)
        area_m2 = float(shapely.union_all(fp.geometry.values).area)
        taken = sorted(str(t) for t in fp.get("taken_at", []) if isinstance(t, str) and t)
        bodies = fp["camera"].value_counts() if "camera" in fp else {}
        pairs += [
            ("Photos", len(fp) + int((ctx.done("footprints") or {}).get("n_skipped") or 0)),
            ("Photos with a footprint", len(fp)),
            ("Camera bodies", "; ".join(f"{k} ({v} photos)" for k, v in bodies.items()) or "–"),
            ("Area covered", f"{area_m2 / 1e4:.2f} ha ({area_m2:,.0f} m²)"),
            ("GSD min / median / max", f"{gsd.min():.2f} / {gsd.median():.2f} / {gsd.max():.2f} cm"),
            ("Flight date", _flight_time(taken)),
            ("Height above ground", _height_line(ctx.done("footprints") or {})),
            ("Heights", "; ".join(sorted(set(fp["height_source"].astype(str)))) if "height_source" in fp else "–"),
            (
                "Vertical datum",
                "; ".join(sorted(set(fp["vertical_datum"].astype(str)))) if "vertical_datum" in fp else "–",
            ),
        ]
    crs = _crs_label(ctx)
    pairs.append(("CRS", crs or "–"))
    if sfm:
        pairs += [
            ("Photos registered (SfM)", f"{sfm.get('registered')} of {sfm.get('photos')}"),
            ("Georeferenced by", sfm.get("georeferenced_by")),
            ("Mean reprojection error", f"{sfm.get('mean_reprojection_error_px', float('nan')):.2f} px"),
        ]
        for label, key in (("GCP RMSE", "gcp_accuracy"), ("Checkpoint RMSE", "checkpoint_accuracy")):
            acc = sfm.get(key)
            if not acc:
                continue
            if acc.get("rmse_3d_m") is not None:
                pairs.append((label, f"{_cm(acc['rmse_3d_m'])} 3D over {acc.get('n')}"))
            else:  # heights not controlled (placeholder GCP heights): say so, not a dash
                what = f"{_cm(acc.get('rmse_horizontal_m'))} horizontal over {acc.get('n')}"
                pairs.append((label, what + " (heights not controlled)"))
    o = ctx.done("ortho")
    if o:
        pairs.append(("Orthophoto", f"{100 * float(o['resolution_m']):.2f} cm/pixel from {o.get('n_used')} photos"))
    d = ctx.done("dem")
    if d:
        pairs.append(
            ("DSM / DTM", f"cells of {d.get('resolution'):g} ({d.get('units', '')}), {d.get('n_points'):,} points")
        )
        heights = heights_from_text(d.get("vertical_crs"))
        why = sfm.get("vertical_crs_from") if sfm else None
        said = heights_label(heights) + ((", from " if heights is not None else ": ") + why if why else "")
        pairs.append(("Heights' datum of the DEMs", said))
    return _kv(pairs)


def _height_line(done: dict[str, Any]) -> str:
    """The cameras' height above the ground as measured (SfM poses over the DSM), and as the
    metadata and the options gave it."""
    measured, meta = (float(done.get(k) or "nan") for k in ("altitude_m", "altitude_metadata_m"))
    if not math.isfinite(measured):
        return "–"
    line = f"{measured:.1f} m measured (SfM cameras over the DSM)"
    if math.isfinite(meta):
        line += f"; {meta:.1f} m from the metadata and the heights given ({(meta - measured) / measured:+.0%})"
    else:
        line += "; none from the metadata"
    return line


def _flight_time(taken: list[str]) -> str:
    """First and last photo's time: '2026-05-14 10:00–10:12' (or two dates)."""
    if not taken:
        return "not in the photos' metadata"
    first, last = (t.replace("T", " ")[:16] for t in (taken[0], taken[-1]))
    return f"{first}–{last[11:]}" if first[:10] == last[:10] else f"{first} – {last}"


def _crs_label(ctx: _Context) -> str:
    """The products' CRS: the orthophoto's, else the SfM's ("" when neither says)."""
    return str((ctx.done("ortho") or {}).get("crs") or (ctx.sfm_report() or {}).get("crs") or "")


def _unit_symbol(unit: str | None) -> str:
    u = (unit or "metre").lower()
    return "ft" if "foot" in u or "feet" in u else ("m" if u.startswith("met") or u == "m" else u)


def _nice_length(target: float) -> float:
    """The longest 1, 2 or 5 times a power of ten not over ``target``: a scale bar's length."""
    if not target > 0:
        return 1.0
    power = 10.0 ** np.floor(np.log10(target))
    return float(max(f * power for f in (1.0, 2.0, 5.0) if f * power <= target))


def _furnish(ax: Any, crs: str, unit: str = "m") -> None:
    """A map's furniture: a scale bar (lower left), a north arrow (the grid's north: the map's
    up; upper left), and axis titles with the unit and the CRS."""
    from mpl_toolkits.axes_grid1.anchored_artists import AnchoredSizeBar

    x0, x1 = ax.get_xlim()
    y0, y1 = ax.get_ylim()
    length = _nice_length(abs(x1 - x0) / 5.0)
    bar = AnchoredSizeBar(
        ax.transData, length, f"{length:g} {unit}", "lower left", pad=0.4, borderpad=0.6, sep=3,
        frameon=True, size_vertical=abs(y1 - y0) / 150.0, fontproperties={"size": 7},
    )  # fmt: skip
    bar.patch.set_alpha(0.8)
    ax.add_artist(bar)
    arrow = {"arrowstyle": "-|>", "color": "k", "lw": 1.2}
    ax.annotate(
        "N", xy=(0.05, 0.95), xytext=(0.05, 0.82), xycoords="axes fraction", textcoords="axes fraction",
        ha="center", va="center", fontsize=9, fontweight="bold", arrowprops=arrow,
    )  # fmt: skip
    from matplotlib.ticker import MaxNLocator

    # the map's coordinates, whole and few (a UTM easting's offset notation reads as nothing)
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.yaxis.set_major_locator(MaxNLocator(4))
    ax.ticklabel_format(useOffset=False, style="plain")
    ax.tick_params(labelsize=7)
    where = f", {crs}" if crs else ""
    ax.set_xlabel(f"easting ({unit}{where})", fontsize=8)
    ax.set_ylabel(f"northing ({unit})", fontsize=8)


def _map_figure(extent: tuple[float, ...], width_in: float = 7.5) -> Any:
    """A figure whose height follows the map's aspect (no band of white above a wide map)."""
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    return _figure(width_in, min(9.0, max(3.0, width_in * aspect * 0.85 + 0.8)))


def _map(ctx: _Context) -> str:
    fp = ctx.footprints()
    if fp is None:
        return _missing("No footprints (the footprints stage did not finish).")
    left = ctx.left_out()
    bounds = (
        fp.total_bounds
        if left is None or left.empty
        else np.r_[
            np.minimum(fp.total_bounds[:2], left.total_bounds[:2]),
            np.maximum(fp.total_bounds[2:], left.total_bounds[2:]),
        ]
    )
    fig = _map_figure(tuple(bounds[[0, 2, 1, 3]]))
    ax = fig.add_subplot()
    has_ortho = _ortho_background(ax, ctx)
    fp.boundary.plot(ax=ax, color="#1f77b4", linewidth=0.6, alpha=0.7, zorder=2)
    if left is not None and not left.empty:  # ground the products lack: drawn, never a silent hole
        left.plot(ax=ax, facecolor="#d62728", edgecolor="#d62728", alpha=0.25, linewidth=0.8, zorder=3)
        ax.fill([], [], color="#d62728", alpha=0.4, label=f"footprint of a photo left out ({len(left)})")
    cams = _sfm_cameras(ctx)
    if cams is not None:
        reg = cams["registered"].astype(bool)
        ax.scatter(
            cams.geometry.x[reg],
            cams.geometry.y[reg],
            s=14,
            c="#2ca02c",
            edgecolor="k",
            lw=0.3,
            label=f"camera, registered ({int(reg.sum())})",
            zorder=4,
        )
        if (~reg).any():
            ax.scatter(
                cams.geometry.x[~reg],
                cams.geometry.y[~reg],
                s=28,
                c="#d62728",
                marker="x",
                label=f"camera, not registered ({int((~reg).sum())})",
                zorder=5,
            )
    else:
        import geopandas as gpd

        pos = gpd.read_file(ctx.path("footprints", "output"), layer="cameras")
        ax.scatter(pos.geometry.x, pos.geometry.y, s=14, c="#2ca02c", edgecolor="k", lw=0.3, label="camera (GPS)")
    gcps = _gcp_positions(ctx)
    if gcps:
        xs, ys = zip(*[(g[1], g[2]) for g in gcps])
        ax.scatter(xs, ys, s=60, marker="^", c="#ff7f0e", edgecolor="k", lw=0.5, label="GCP", zorder=6)
    ax.plot([], [], color="#1f77b4", lw=0.8, label=f"photo footprint ({len(fp)})")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    _furnish(ax, _crs_label(ctx))
    note = "" if has_ortho else _missing("No orthophoto to draw under the footprints.")
    return _png(fig, "footprints and camera positions over the orthophoto") + note


#: How each position accuracy class is drawn on the map.
_FIX_STYLE = {
    "fixed": ("#1a7f37", "RTK fixed"),
    "float": ("#e6a100", "RTK float"),
    "single": ("#b00020", "single point (fix lost)"),
    "stated": ("#1f77b4", "accuracy stated"),
    "consumer": ("#999999", "consumer GPS"),
}


def _position_accuracy(ctx: _Context) -> str:
    """Each photo's position accuracy class on a map, and per class the accuracy stated against
    what the bundle adjustment measured; a positions file and the time lag found in it."""
    sfm = ctx.sfm_report()
    acc = (sfm or {}).get("gps_accuracy")
    if not acc:
        return _missing(
            "No photo states its position accuracy (consumer GPS): every position is weighed at the "
            "SfM's gps_sigma_m, and the GCPs (if any) carry the georeference."
        )
    parts: list[str] = []
    cams = _sfm_cameras(ctx)
    if cams is not None and "gps_fix" in cams:
        fig = _map_figure(tuple(cams.total_bounds[[0, 2, 1, 3]]), width_in=6.5)
        ax = fig.add_subplot()
        _ortho_background(ax, ctx)
        for fix, (colour, label) in _FIX_STYLE.items():
            sel = cams["gps_fix"] == fix
            if sel.any():
                ax.scatter(
                    cams.geometry.x[sel], cams.geometry.y[sel], s=22, c=colour, edgecolor="k", lw=0.3,
                    label=f"{label} ({int(sel.sum())})", zorder=4,
                )  # fmt: skip
        ax.set_aspect("equal")
        ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
        _furnish(ax, _crs_label(ctx))
        parts.append(_png(fig, "camera positions by accuracy class"))
    rows = []
    for fix, c in sorted(acc["classes"].items(), key=lambda kv: -kv[1]["photos"]):
        agrees = c.get("rmse_h_m") is not None and c["rmse_h_m"] <= 2.0 * c["sigma_h_m"]
        rows.append(
            [
                _FIX_STYLE.get(fix, ("", fix))[1],
                c["photos"],
                _cm(c["sigma_h_m"]),
                _cm(c["sigma_v_m"]),
                _cm(c.get("rmse_h_m")),
                _cm(c.get("rmse_v_m")),
                '<span class="ok">agrees</span>' if agrees else '<span class="warn">off its stated accuracy</span>',
            ]
        )
    if acc.get("consumer"):
        rows.append([_FIX_STYLE["consumer"][1], acc["consumer"], "–", "–", "–", "–", "weighed at gps_sigma_m"])
    parts.append(
        _table(
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
        parts.append(_kv(pairs))
    return "".join(parts)


def _sfm_cameras(ctx: _Context) -> Any:
    path = ctx.path("sfm", "cameras")
    if path is None:
        return None
    import geopandas as gpd

    return gpd.read_file(path, layer="cameras")


def _gcp_positions(ctx: _Context) -> list[tuple[str, float, float, float]]:
    """(name, x, y, z) of the GCPs in the found gcp_list.txt (the CRS of the products)."""
    used = ctx.values("sfm").get("gcp_list")  # found by gcp-find, or given as observations
    path = Path(used) if isinstance(used, str) and Path(used).is_file() else None
    if path is None:
        return []
    from pyproj import CRS

    gcps = read_gcp_file(path)
    points = list(gcps.by_name().items())
    # the products' CRS, whatever CRS the GCP list is in (EPSG:4326 lon/lat drew at (0, 0) of UTM axes)
    target = _crs_label(ctx)
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


def _residuals(ctx: _Context, sfm: dict[str, Any]) -> _Residuals:
    where = {n: (x, y) for n, x, y, _ in _gcp_positions(ctx)}
    res = [r for r in sfm.get("gcps", []) if r.get("name") in where and r.get("dx_m") is not None]
    xy = np.array([where[r["name"]] for r in res], float).reshape(-1, 2)
    d = np.array([[r["dx_m"], r["dy_m"]] for r in res], float).reshape(-1, 2)
    span = max(float(np.ptp(xy[:, 0])), float(np.ptp(xy[:, 1])), 1.0) if res else 1.0
    longest = max(float(np.nanmax(np.hypot(d[:, 0], d[:, 1]))), 1e-6) if res else 1e-6
    return _Residuals(res, xy, d, span, longest)


def _write_residual_layers(ctx: _Context, project: Path) -> Path | None:
    """The GCPs and checkpoints at their surveyed places with their residuals (``gcps``), and each
    horizontal residual as a line drawn ``exaggeration`` times its length (``residuals``), as the
    report's plot draws them."""
    found = _residuals(ctx, ctx.sfm_report() or {})
    res, xy, d = found.records, found.xy, found.d
    crs = _crs_label(ctx)
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


def _overlap(ctx: _Context) -> str:
    path = ctx.path("footprints", "overlap")
    if path is None:
        return _missing("No overlap raster.")
    from matplotlib.colors import BoundaryNorm, ListedColormap

    data, valid, extent, _ = _read_raster(path, [1])
    count = np.where(valid, data[0], 0).astype(int)
    top = max(1, int(count.max()))
    levels = [0, 1, 2, 3, 5, 9, max(10, top + 1)]
    colours = ["#ffffff", "#d73027", "#fc8d59", "#fee08b", "#91cf60", "#1a9850"]
    norm = BoundaryNorm(levels, len(colours))
    fig = _map_figure(extent, 7.0)
    ax = fig.add_subplot()
    im = ax.imshow(count, extent=extent, cmap=ListedColormap(colours), norm=norm, interpolation="nearest")
    cbar = fig.colorbar(im, ax=ax, shrink=0.8, ticks=[0.5, 1.5, 2.5, 4, 7, (9 + levels[-1]) / 2])
    cbar.ax.set_yticklabels(["0", "1", "2", "3–4", "5–8", f"9+ (max {top})"])
    cbar.set_label("photos covering the ground")
    ax.set_aspect("equal")
    _furnish(ax, _crs_label(ctx))
    covered = count > 0
    rows = []
    for n in (1, 2, 3, 5, 9):
        share = float((count[covered] >= n).mean()) if covered.any() else 0.0
        rows.append([f"≥ {n}", f"{100 * share:.1f} %"])
    return (
        _png(fig, "overlap map")
        + "<p>Share of the covered ground seen by at least N photos (≥ 5 is what a good dense surface needs):</p>"
        + _table(["photos", "share of covered ground"], rows)
    )


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
                _cm(a.get("rmse_x_m")),
                _cm(a.get("rmse_y_m")),
                _cm(a.get("rmse_horizontal_m")),
                _cm(a.get("rmse_z_m")),
                _cm(a.get("rmse_3d_m")),
                _cm(a.get("ce90_m")),
                _cm(a.get("le90_m")),
            ]
        )
    return rows


def _gcps(ctx: _Context) -> str:
    given = "gcp-find" in ctx.stages or bool(ctx.values("sfm").get("gcp_list"))
    sfm = ctx.sfm_report()
    parts: list[str] = []
    g = ctx.done("gcp-find")
    if "gcp-find" not in ctx.stages and given:
        parts.append(f"<p>GCP observations given: {html.escape(str(ctx.values('sfm')['gcp_list']))}</p>")
    if not given:
        return _missing(
            "No GCP file was given: the products' absolute accuracy is the photos' GPS "
            + (f"(SfM: {sfm.get('georeferenced_by')})." if sfm else ".")
        )
    if g is not None:
        parts.append(
            _kv(
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
        return "".join(parts) or _missing("SfM did not finish.")
    rows = [
        [
            r.get("name"),
            r.get("role"),
            r.get("observations"),
            r.get("inliers"),
            _cm(r.get("dx_m")),
            _cm(r.get("dy_m")),
            _cm(r.get("dz_m")),
            None if r.get("reprojection_px") is None else f"{r['reprojection_px']:.2f}",
        ]
        for r in sfm["gcps"]
    ]
    parts.append(
        "<h3>Residuals per point</h3><p>Measured minus surveyed, in the products' CRS.</p>"
        + _table(["name", "role", "photos", "inliers", "dX", "dY", "dZ", "reprojection (px)"], rows)
    )
    acc = _accuracy_rows(sfm)
    if acc:
        parts.append(
            "<h3>Accuracy</h3>"
            + _table(["", "n", "RMSE X", "RMSE Y", "RMSE XY", "RMSE Z", "RMSE 3D", "CE90", "LE90"], acc)
            + f'<p class="muted">{html.escape(str(sfm.get("ce90_le90", "")))}</p>'
        )
    parts.append(_residual_plot(ctx, sfm))
    return "".join(parts)


def _residual_plot(ctx: _Context, sfm: dict[str, Any]) -> str:
    found = _residuals(ctx, sfm)
    res, scale, span, longest = found.records, found.scale, found.span_m, found.longest_m
    if not res:
        return ""
    (xs, ys), (dx, dy) = found.xy.T, found.d.T
    dz = np.array([r["dz_m"] if r.get("dz_m") is not None else np.nan for r in res], dtype=float)
    fig = _figure(7.0, 5.5)
    ax = fig.add_subplot()
    _ortho_background(ax, ctx)
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
    _furnish(ax, _crs_label(ctx))
    return "<h3>Residual vectors</h3>" + _png(fig, "GCP and checkpoint residual vectors")


def _reprojection(ctx: _Context) -> str:
    model = ctx.path("sfm", "model")
    sfm = ctx.sfm_report()
    if model is None or sfm is None:
        return _missing("SfM did not finish.")

    pycolmap = load_pycolmap()

    rec = pycolmap.Reconstruction(str(model))
    errors = np.array([p.error for p in rec.points3D.values()], dtype=float)
    errors = errors[np.isfinite(errors)]
    if errors.size == 0:
        return _missing("The model has no tie points.")
    fig = _figure(7.0, 3.5)
    ax = fig.add_subplot()
    top = float(np.percentile(errors, 99.5))
    ax.hist(np.clip(errors, 0, top), bins=60, color="#4c72b0")
    ax.axvline(float(np.mean(errors)), color="k", ls="--", lw=1, label=f"mean {np.mean(errors):.2f} px")
    ax.set_xlabel(f"mean reprojection error of a tie point (px; the last bin holds all ≥ {top:.2f})")
    ax.set_ylabel("tie points")
    ax.legend(fontsize=8)
    return _png(fig, "reprojection error histogram") + _kv(
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


def _not_used(ctx: _Context) -> str:

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
    return _table(["photo", "stage", "why"], rows)


def _elevation(ctx: _Context) -> str:
    d = ctx.done("dem")
    if d is None:
        return _missing("The dem stage did not finish.")
    from matplotlib.colors import LightSource, Normalize

    parts = []
    fig = _figure(7.5, 3.8)
    for i, (label, key) in enumerate((("DSM", "dsm"), ("DTM", "dtm"))):
        path = ctx.path("dem", key)
        if path is None:
            continue
        data, valid, extent, unit = _read_raster(path, [1])
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
        _furnish(ax, _crs_label(ctx), _unit_symbol(unit))
    parts.append(_png(fig, "DSM and DTM hillshades"))
    dense = ctx.dense_report()
    pairs: list[tuple[str, Any]] = [
        ("Point cloud", "lidar (given)" if "dense" not in ctx.stages else "dense, from the photos"),
        ("Points / ground points", f"{d.get('n_points'):,} / {d.get('n_ground'):,}"),
        ("Cell size", f"{d.get('resolution'):g} ({d.get('units', '')})"),
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
    parts.append(_kv(pairs))
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


def _ortho(ctx: _Context) -> str:
    o = ctx.ortho_report()
    path = ctx.path("ortho", "preview")
    if o is None:
        return _missing("The ortho stage did not finish.")
    parts = [_png_file(path, "orthophoto preview")] if path is not None else []
    covered = float(o.get("coverage_px") or 0)
    holes = float(o.get("holes_left_px") or 0)
    parts.append(
        _kv(
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


def _ortho_sources_map(ctx: _Context, o: dict[str, Any]) -> str:
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
        scale = max(1.0, max(ds.width, ds.height) / _MAX_RASTER_PX)
        shape = (max(1, round(ds.height / scale)), max(1, round(ds.width / scale)))
        how = ds.read(2, out_shape=shape, resampling=Resampling.nearest)
        b = ds.bounds
    extent = (b.left, b.right, b.bottom, b.top)
    fig = _figure(7.0, 4.8)
    ax = fig.add_subplot()
    path = ctx.path("ortho", "output")
    if path is not None:
        data, valid, o_extent, _ = _read_raster(path, [1, 2, 3])
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
        d, d_valid, d_extent, _ = _read_raster(dsm_source, [1])
        tint(d_valid & (np.rint(d[0]) != MEASURED), (0.0, 0.35, 1.0), 0.35, d_extent, "on an interpolated DSM")
    tint(how == OCCLUDED, (0.9, 0.0, 0.9), 1.0, extent, "seen by no photo (occluded)")
    tint(how == INPAINTED, (1.0, 0.1, 0.0), 1.0, extent, "inpainted")
    ax.set_xlim(extent[0], extent[1])
    ax.set_ylim(extent[2], extent[3])
    ax.set_aspect("equal")
    ax.legend(handles=legend, fontsize=8, loc="lower right")
    _furnish(ax, _crs_label(ctx))
    ax.set_title("Where the orthophoto is not plainly seen on a measured surface", fontsize=10)
    return _png(fig, "orthophoto sources map")


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


def _seams(ctx: _Context) -> str:
    o = ctx.ortho_report()
    if o is None:
        return _missing("The ortho stage did not finish.")
    gains = o.get("gains_bgr") or {}
    parts = [
        _kv(
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
        fig = _figure(7.5, 3.2)
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
        parts.append(_png(fig, "colour balance gain per photo"))
        far = [n for n, v in zip(names, g) if np.max(np.abs(np.log(np.clip(v, 1e-3, None)))) > math.log(1.25)]
        if far:
            parts.append(
                f'<p class="warn">Gains beyond ±25 % (exposure steps?): {html.escape(", ".join(far[:20]))}</p>'
            )
    return "".join(parts)


def _timing(ctx: _Context) -> str:

    current = ctx.ledger.get("current_run") or {}
    this_run = current.get("stages", {})
    names = [s.name for s in STAGES if s.name in ctx.stages and s.name != "report"]
    rows = []
    secs = []
    for n in names:
        rec = ctx.stages[n]
        mem = rec.get("peak_memory_mb") or {}
        secs.append(float(rec.get("seconds") or 0.0))
        started = rec.get("started")
        rows.append(
            [
                n,
                _Raw(_status_html(rec.get("status", ""))),
                this_run.get(n, "–"),
                _duration(secs[-1]),
                _megabytes(mem.get("main")),
                _megabytes(mem.get("with_workers")),
                time.strftime("%Y-%m-%d %H:%M", time.localtime(started)) if started else "–",
            ]
        )
    header = ["stage", "status", "this run", "time", "peak memory (main)", "peak memory (with workers)", "made"]
    parts = [_table(header, rows)]
    if current:
        parts.append(
            f"<p>The run that made this report: {current['seconds_before_report']:.1f} s before the report, of which "
            f"{current['overhead_seconds']:.2f} s bookkeeping (hashing inputs, the ledger).</p>"
        )
    if secs and sum(secs) > 0:
        fig = _figure(7.0, 0.4 * len(names) + 1.0)
        ax = fig.add_subplot()
        ax.barh(names[::-1], secs[::-1], color="#4c72b0")
        ax.set_xlabel("seconds (when last made)")
        parts.append(_png(fig, "time per stage"))
    return "".join(parts)


def _duration(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def _megabytes(mb: Any) -> str:
    if not isinstance(mb, (int, float)) or not math.isfinite(mb):
        return "–"
    return f"{mb:.0f} MB" if mb < 1024 else f"{mb / 1024:.2f} GB"


def _status_html(status: str) -> str:
    cls = {"done": "ok", "failed": "bad", "canceled": "bad", "running": "bad"}.get(status, "")
    return f'<span class="{cls}">{html.escape(status)}</span>'


def _parameters(ctx: _Context) -> str:

    parts = []
    for s in STAGES:
        rec = ctx.stages.get(s.name)
        if not rec:
            continue
        values = rec.get("values", {})
        rows = [[k, json.dumps(v) if not isinstance(v, str) else v] for k, v in sorted(values.items())]
        parts.append(f"<h3>{html.escape(s.name)}</h3>" + _table(["parameter", "value"], rows, "params"))
    versions: dict[str, str] = next((r["versions"] for r in ctx.stages.values() if r.get("versions")), {})
    if versions:
        parts.append("<h3>Software</h3>" + _kv(sorted(versions.items())))
    return "".join(parts)


def _notes(ctx: _Context) -> str:
    # one line per message, with its level: a note the stage also warned about is a warning
    rows = []
    warned = {(name, w) for name, rec in ctx.stages.items() for w in rec.get("warnings", [])}
    for name, rep in (("sfm", ctx.sfm_report()), ("dense", ctx.dense_report()), ("ortho", ctx.ortho_report())):
        for n in (rep or {}).get("notes", []):
            if (name, n) not in warned:
                rows.append([name, "note", n])
    for name, rec in ctx.stages.items():
        for w in dict.fromkeys(rec.get("warnings", [])):
            rows.append([name, "warning", w])
    return _table(["stage", "kind", "message"], rows) if rows else "<p>None.</p>"


_SECTIONS: list[tuple[str, Callable[[_Context], str | None]]] = [
    ("Quality check", _quality),
    ("Dataset summary", _summary),
    ("Footprints and camera positions", _map),
    ("Camera position accuracy", _position_accuracy),
    ("Overlap", _overlap),
    ("Ground control and checkpoints", _gcps),
    ("Reprojection error", _reprojection),
    ("Photos not used", _not_used),
    ("DSM and DTM", _elevation),
    ("Orthophoto", _ortho),
    ("Seams and colour balance", _seams),
    ("Time and memory per stage", _timing),
    ("Notes and warnings", _notes),
    ("Parameters", _parameters),
]


_CSS = """
body { font: 14px/1.45 system-ui, sans-serif; color: #222; max-width: 60em; margin: 1.5em auto; padding: 0 1em; }
h1 { font-size: 1.6em; margin-bottom: 0.2em; }
h2 { border-bottom: 2px solid #4c72b0; padding-bottom: 0.15em; margin-top: 1.6em; }
h3 { font-size: 1.05em; margin: 1.2em 0 0.4em; }
table { border-collapse: collapse; margin: 0.5em 0; font-size: 0.92em; }
th, td { border: 1px solid #ccc; padding: 0.2em 0.5em; text-align: left; vertical-align: top; }
thead th { background: #eef2f8; }
table.kv th { background: #f6f6f6; font-weight: 600; width: 17em; }
table.params td { font-family: ui-monospace, monospace; font-size: 0.9em; word-break: break-all; }
img.fig { max-width: 100%; height: auto; display: block; margin: 0.5em 0; }
.muted { color: #666; }
.ok { color: #1a7f37; }
.bad, .problem { color: #b00020; font-weight: 600; }
.warn { color: #9a6700; }
.banner { border: 2px solid #b00020; background: #fdecee; padding: 0.6em 1em; margin: 1em 0; }
.banner.good { border-color: #1a7f37; background: #eaf6ec; }
.banner.amber { border-color: #9a6700; background: #fff8e5; }
.state { font-weight: 600; padding: 0 0.4em; border-radius: 3px; color: #fff; }
.state.green { background: #1a7f37; } .state.amber { background: #9a6700; } .state.red { background: #b00020; }
.state.not-measured { background: #999; }
table.quality td:nth-child(-n+1), table.quality td:nth-child(n+3):nth-child(-n+5) { white-space: nowrap; }
nav ol { columns: 2; font-size: 0.95em; }
@media print {
  body { max-width: none; margin: 0; font-size: 11pt; }
  section { break-inside: avoid-page; }
  h2 { break-after: avoid; }
  nav { display: none; }
}
"""


def _page(ctx: _Context, sections: list[str]) -> str:

    started = (ctx.ledger.get("current_run") or {}).get("started")
    when = time.strftime("%Y-%m-%d %H:%M", time.localtime(started)) if started else "–"
    flagged = _flagged(ctx)
    measured = [c for c in ctx.checks if c.state != "not measured"]
    items = "".join(
        f"<li><b>{html.escape(p.get('stage', ''))}</b>: {html.escape(p.get('message', ''))}</li>" for p in ctx.problems
    ) + "".join(
        f'<li><a href="#quality-check">{html.escape(c.label)}</a>: {html.escape(c.shown)} '
        f"({c.state}; green {html.escape(c.green)})</li>"
        for c in sorted(flagged, key=lambda c: c.state != "red")
    )
    if ctx.verdict == "red":
        banner = (
            f'<div class="banner problem"><p>Quality: RED. Problems ({len(ctx.problems) + len(flagged)}):</p>'
            f"<ul>{items}</ul></div>"
        )
    elif ctx.verdict == "amber":
        banner = f'<div class="banner amber"><p>Quality: AMBER. To look at ({len(flagged)}):</p><ul>{items}</ul></div>'
    else:
        banner = (
            f'<div class="banner good">Quality: GREEN. Every stage finished; each of the {len(measured)} items '
            "measured is within its green threshold; no problem found.</div>"
        )
    toc = "".join(f'<li><a href="#{_anchor(t)}">{html.escape(t)}</a></li>' for t, _ in _SECTIONS)
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>geoortho quality report: {html.escape(ctx.project.name)}</title>"
        f"<style>{_CSS}</style></head><body>"
        f"<h1>Quality report: {html.escape(ctx.project.name)}</h1>"
        f'<p class="muted">geoortho {html.escape(__version__)} · project {html.escape(str(ctx.project))} · '
        f"run started {when}</p>"
        f"{banner}<nav><ol>{toc}</ol></nav>" + "\n".join(sections) + "</body></html>\n"
    )
