"""What the report's sections read (the project's ledger and each stage's reports, loaded once) and the
helpers they draw with: figures as embedded PNG, tables, map furniture (scale bar, north arrow, axes).
"""

from __future__ import annotations

import base64
import html
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.chain.ledger import from_ledger

_DPI = 110
MAX_RASTER_PX = 900  # rasters are drawn from their overviews at about this size


# --- what the sections read ----------------------------------------------------------------------


class ReportContext:
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


def new_figure(width_in: float = 7.0, height_in: float = 4.5) -> Any:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width_in, height_in), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def png_img(fig: Any, alt: str) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    data = base64.b64encode(buf.getvalue()).decode("ascii")
    return f'<img class="fig" alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def png_file(path: Path, alt: str) -> str:
    data = base64.b64encode(path.read_bytes()).decode("ascii")
    return f'<img class="fig" alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def read_raster(path: Path, bands: list[int] | None = None) -> tuple[np.ndarray, np.ndarray, tuple[float, ...], Any]:
    """A raster decimated to about _MAX_RASTER_PX (from its overviews): values (bands, rows, cols),
    valid mask, extent (left, right, bottom, top) and its CRS's linear unit name."""
    import rasterio
    from rasterio.enums import Resampling

    with rasterio.open(path) as src:
        scale = max(1.0, max(src.width, src.height) / MAX_RASTER_PX)
        shape = (max(1, round(src.height / scale)), max(1, round(src.width / scale)))
        idx = bands or list(range(1, src.count + 1))
        data = src.read(idx, out_shape=(len(idx), *shape), resampling=Resampling.average, masked=True)
        mask = src.dataset_mask(out_shape=shape, resampling=Resampling.nearest) > 0
        valid = mask & ~np.ma.getmaskarray(data).any(axis=0)
        b = src.bounds
        unit = src.crs.linear_units if src.crs is not None else ""
    return np.ma.getdata(data), valid, (b.left, b.right, b.bottom, b.top), unit


def ortho_background(ax: Any, ctx: ReportContext) -> bool:
    """The orthophoto under a map, when there is one."""
    path = ctx.path("ortho", "output")
    if path is None:
        return False
    data, valid, extent, _ = read_raster(path, [1, 2, 3])
    rgba = np.dstack([np.moveaxis(data, 0, -1).astype(np.uint8), (valid * 255).astype(np.uint8)])
    ax.imshow(rgba, extent=extent, interpolation="bilinear", zorder=0)
    return True


def html_table(header: list[str], rows: list[list[Any]], cls: str = "") -> str:
    head = "".join(f"<th>{html.escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{_cell(c)}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>'


def _cell(v: Any) -> str:
    if isinstance(v, RawHtml):
        return v.html
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 100 else f"{v:,.0f}"  # never 1.01e+03
    return html.escape(str(v))


@dataclass(frozen=True)
class RawHtml:
    html: str


def key_values(pairs: list[tuple[str, Any]]) -> str:
    rows = "".join(f"<tr><th>{html.escape(k)}</th><td>{_cell(v)}</td></tr>" for k, v in pairs)
    return f'<table class="kv">{rows}</table>'


def as_cm(v: Any) -> str:
    return "–" if v is None else f"{100 * float(v):.1f} cm"


def cell_size_text(dem: dict[str, Any]) -> str:
    """dem's cell size in metres, and in its rasters' own units where they are not metres (a
    project's ledger from before ``resolution_m``: as it was recorded, with its units)."""
    units = str(dem.get("units", ""))
    if dem.get("resolution_m") is None:
        return f"{dem.get('resolution'):g} ({units})"
    own = "" if "horizontal metre" in units else f" = {dem.get('resolution_crs_units'):g} ({units})"
    return f"{float(dem['resolution_m']):g} m{own}"


def missing_note(what: str) -> str:
    return f'<p class="muted">{html.escape(what)}</p>'


def anchor_of(title: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in title.lower()).strip("-")


def crs_label(ctx: ReportContext) -> str:
    """The products' CRS: the orthophoto's, else the SfM's ("" when neither says)."""
    return str((ctx.done("ortho") or {}).get("crs") or (ctx.sfm_report() or {}).get("crs") or "")


def unit_symbol(unit: str | None) -> str:
    u = (unit or "metre").lower()
    return "ft" if "foot" in u or "feet" in u else ("m" if u.startswith("met") or u == "m" else u)


def _nice_length(target: float) -> float:
    """The longest 1, 2 or 5 times a power of ten not over ``target``: a scale bar's length."""
    if not target > 0:
        return 1.0
    power = 10.0 ** np.floor(np.log10(target))
    return float(max(f * power for f in (1.0, 2.0, 5.0) if f * power <= target))


def furnish(ax: Any, crs: str, unit: str = "m") -> None:
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


def map_figure(extent: tuple[float, ...], width_in: float = 7.5) -> Any:
    """A figure whose height follows the map's aspect (no band of white above a wide map)."""
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    return new_figure(width_in, min(9.0, max(3.0, width_in * aspect * 0.85 + 0.8)))


def duration(seconds: float) -> str:
    return f"{seconds:.1f} s" if seconds < 120 else f"{seconds / 60:.1f} min"


def megabytes(mb: Any) -> str:
    if not isinstance(mb, (int, float)) or not math.isfinite(mb):
        return "–"
    return f"{mb:.0f} MB" if mb < 1024 else f"{mb / 1024:.2f} GB"


def status_html(status: str) -> str:
    cls = {"done": "ok", "failed": "bad", "canceled": "bad", "running": "bad"}.get(status, "")
    return f'<span class="{cls}">{html.escape(status)}</span>'
