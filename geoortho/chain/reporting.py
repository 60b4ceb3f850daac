"""The quality report of a ``run`` project: one self-contained HTML file a client can read.

Everything in it is read from the project: ``run.json`` (stages, options, timings, memory,
problems) and each stage's own products and reports, so its numbers are theirs. Figures are
drawn with matplotlib (Agg, no pyplot state) and embedded as PNG data URIs: the file needs no
network and prints to PDF from a browser. A section whose products are missing says so; one
that cannot be drawn says why, in red, instead of taking the report down.

Here: :func:`report`, the grade, the summary, the map, the timing and the page. Beside it:
:mod:`.report_base` (what the sections read, the drawing helpers), :mod:`.report_accuracy` and
:mod:`.report_products` (their sections).
"""

from __future__ import annotations

import html
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.chain.ledger import LEDGER_NAME, from_ledger, ledger_problem
from geoortho.chain.qgis_project import write_qgis_project
from geoortho.chain.quality import assess, verdict
from geoortho.chain.report_accuracy import (
    gcp_positions,
    gcps_section,
    not_used_section,
    position_accuracy_section,
    reprojection_section,
    sfm_cameras,
    write_residual_layers,
)
from geoortho.chain.report_base import (
    RawHtml,
    ReportContext,
    anchor_of,
    as_cm,
    cell_size_text,
    crs_label,
    duration,
    furnish,
    html_table,
    key_values,
    map_figure,
    megabytes,
    missing_note,
    new_figure,
    ortho_background,
    png_img,
    read_raster,
    status_html,
)
from geoortho.chain.report_products import (
    change_section,
    elevation_section,
    mesh_section,
    ortho_section,
    seams_section,
    volumes_section,
)
from geoortho.chain.stages import REPORT_NAME, STAGES
from geoortho.core.crs import heights_from_text, heights_label
from geoortho.core.folders import refuse_writing_into
from geoortho.core.outputs import write_json, write_text
from geoortho.errors import InputError, ParameterError
from geoortho.feedback import Feedback, as_feedback
from geoortho.version import __version__

__all__ = ["ReportResult", "report"]


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
    ctx = ReportContext(project, ledger)
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
            sections.append(f'<section id="{anchor_of(title)}"><h2>{html.escape(title)}</h2>\n{body}\n</section>')
    page = _page(ctx, sections)
    quality = project / "quality.json"
    graded = {"verdict": ctx.verdict, "checks": [asdict(c) for c in ctx.checks], "problems": ctx.problems}
    write_json(quality, {"version": QUALITY_VERSION, **graded})
    write_text(out, page)
    try:  # the products as one styled QGIS project: a convenience, never the report's failure
        write_residual_layers(ctx, project)
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


def _grade(ctx: ReportContext) -> None:
    """The quality check of what the stages measured (see geoortho.chain.quality)."""

    try:
        ctx.checks = assess(
            ctx.sfm_report(), ctx.dense_report(), ctx.done("dem"), ctx.ortho_report(), ctx.done("footprints")
        )
    except (TypeError, AttributeError, ValueError, KeyError) as e:  # a hand-edited or damaged stage report
        ctx.problem("report", f"the stage reports hold values of the wrong type ({type(e).__name__}: {e})")
        ctx.checks = assess(None, None, None, None, None)
    ctx.verdict = verdict(ctx.checks, failed=bool(ctx.problems))


def _flagged(ctx: ReportContext) -> list[Any]:
    return [c for c in ctx.checks if c.state in ("amber", "red")]


def _quality(ctx: ReportContext) -> str:
    rows = [
        [RawHtml(f'<span class="state {c.state.replace(" ", "-")}">{html.escape(c.state)}</span>'), c.label, c.shown,
         c.green, c.red, c.detail]
        for c in ctx.checks
    ]  # fmt: skip
    return (
        '<p class="muted">Each item measured, graded against the thresholds in geoortho.chain.quality '
        "(the README gives each one's reason); the verdict is the worst item's.</p>"
        + html_table(["state", "item", "measured", "green", "red", "detail"], rows, "quality")
    )


# --- the sections --------------------------------------------------------------------------------


def _summary(ctx: ReportContext) -> str:
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
    crs = crs_label(ctx)
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
                pairs.append((label, f"{as_cm(acc['rmse_3d_m'])} 3D over {acc.get('n')}"))
            else:  # heights not controlled (placeholder GCP heights): say so, not a dash
                what = f"{as_cm(acc.get('rmse_horizontal_m'))} horizontal over {acc.get('n')}"
                pairs.append((label, what + " (heights not controlled)"))
    o = ctx.done("ortho")
    if o:
        pairs.append(("Orthophoto", f"{100 * float(o['resolution_m']):.2f} cm/pixel from {o.get('n_used')} photos"))
    d = ctx.done("dem")
    if d:
        pairs.append(("DSM / DTM", f"cells of {cell_size_text(d)}, {d.get('n_points'):,} points"))
        heights = heights_from_text(d.get("vertical_crs"))
        why = sfm.get("vertical_crs_from") if sfm else None
        said = heights_label(heights) + ((", from " if heights is not None else ": ") + why if why else "")
        pairs.append(("Heights' datum of the DEMs", said))
    return key_values(pairs)


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


def _map(ctx: ReportContext) -> str:
    fp = ctx.footprints()
    if fp is None:
        return missing_note("No footprints (the footprints stage did not finish).")
    left = ctx.left_out()
    bounds = (
        fp.total_bounds
        if left is None or left.empty
        else np.r_[
            np.minimum(fp.total_bounds[:2], left.total_bounds[:2]),
            np.maximum(fp.total_bounds[2:], left.total_bounds[2:]),
        ]
    )
    fig = map_figure(tuple(bounds[[0, 2, 1, 3]]))
    ax = fig.add_subplot()
    has_ortho = ortho_background(ax, ctx)
    fp.boundary.plot(ax=ax, color="#1f77b4", linewidth=0.6, alpha=0.7, zorder=2)
    if left is not None and not left.empty:  # ground the products lack: drawn, never a silent hole
        left.plot(ax=ax, facecolor="#d62728", edgecolor="#d62728", alpha=0.25, linewidth=0.8, zorder=3)
        ax.fill([], [], color="#d62728", alpha=0.4, label=f"footprint of a photo left out ({len(left)})")
    cams = sfm_cameras(ctx)
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
    gcps = gcp_positions(ctx)
    if gcps:
        xs, ys = zip(*[(g[1], g[2]) for g in gcps])
        ax.scatter(xs, ys, s=60, marker="^", c="#ff7f0e", edgecolor="k", lw=0.5, label="GCP", zorder=6)
    ax.plot([], [], color="#1f77b4", lw=0.8, label=f"photo footprint ({len(fp)})")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    furnish(ax, crs_label(ctx))
    note = "" if has_ortho else missing_note("No orthophoto to draw under the footprints.")
    return png_img(fig, "footprints and camera positions over the orthophoto") + note


def _overlap(ctx: ReportContext) -> str:
    path = ctx.path("footprints", "overlap")
    if path is None:
        return missing_note("No overlap raster.")
    from matplotlib.colors import BoundaryNorm, ListedColormap

    data, valid, extent, _ = read_raster(path, [1])
    count = np.where(valid, data[0], 0).astype(int)
    top = max(1, int(count.max()))
    levels = [0, 1, 2, 3, 5, 9, max(10, top + 1)]
    colours = ["#ffffff", "#d73027", "#fc8d59", "#fee08b", "#91cf60", "#1a9850"]
    norm = BoundaryNorm(levels, len(colours))
    fig = map_figure(extent, 7.0)
    ax = fig.add_subplot()
    im = ax.imshow(count, extent=extent, cmap=ListedColormap(colours), norm=norm, interpolation="nearest")
    cbar = fig.colorbar(im, ax=ax, shrink=0.8, ticks=[0.5, 1.5, 2.5, 4, 7, (9 + levels[-1]) / 2])
    cbar.ax.set_yticklabels(["0", "1", "2", "3–4", "5–8", f"9+ (max {top})"])
    cbar.set_label("photos covering the ground")
    ax.set_aspect("equal")
    furnish(ax, crs_label(ctx))
    covered = count > 0
    rows = []
    for n in (1, 2, 3, 5, 9):
        share = float((count[covered] >= n).mean()) if covered.any() else 0.0
        rows.append([f"≥ {n}", f"{100 * share:.1f} %"])
    return (
        png_img(fig, "overlap map")
        + "<p>Share of the covered ground seen by at least N photos (≥ 5 is what a good dense surface needs):</p>"
        + html_table(["photos", "share of covered ground"], rows)
    )


def _timing(ctx: ReportContext) -> str:

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
                RawHtml(status_html(rec.get("status", ""))),
                this_run.get(n, "–"),
                duration(secs[-1]),
                megabytes(mem.get("main")),
                megabytes(mem.get("with_workers")),
                time.strftime("%Y-%m-%d %H:%M", time.localtime(started)) if started else "–",
            ]
        )
    header = ["stage", "status", "this run", "time", "peak memory (main)", "peak memory (with workers)", "made"]
    parts = [html_table(header, rows)]
    if current:
        parts.append(
            f"<p>The run that made this report: {current['seconds_before_report']:.1f} s before the report, of which "
            f"{current['overhead_seconds']:.2f} s bookkeeping (hashing inputs, the ledger).</p>"
        )
    if secs and sum(secs) > 0:
        fig = new_figure(7.0, 0.4 * len(names) + 1.0)
        ax = fig.add_subplot()
        ax.barh(names[::-1], secs[::-1], color="#4c72b0")
        ax.set_xlabel("seconds (when last made)")
        parts.append(png_img(fig, "time per stage"))
    return "".join(parts)


def _parameters(ctx: ReportContext) -> str:

    parts = []
    for s in STAGES:
        rec = ctx.stages.get(s.name)
        if not rec:
            continue
        values = rec.get("values", {})
        rows = [[k, json.dumps(v) if not isinstance(v, str) else v] for k, v in sorted(values.items())]
        parts.append(f"<h3>{html.escape(s.name)}</h3>" + html_table(["parameter", "value"], rows, "params"))
    versions: dict[str, str] = next((r["versions"] for r in ctx.stages.values() if r.get("versions")), {})
    if versions:
        parts.append("<h3>Software</h3>" + key_values(sorted(versions.items())))
    return "".join(parts)


def _notes(ctx: ReportContext) -> str:
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
    return html_table(["stage", "kind", "message"], rows) if rows else "<p>None.</p>"


_SECTIONS: list[tuple[str, Callable[[ReportContext], str | None]]] = [
    ("Quality check", _quality),
    ("Dataset summary", _summary),
    ("Footprints and camera positions", _map),
    ("Camera position accuracy", position_accuracy_section),
    ("Overlap", _overlap),
    ("Ground control and checkpoints", gcps_section),
    ("Reprojection error", reprojection_section),
    ("Photos not used", not_used_section),
    ("DSM and DTM", elevation_section),
    ("Orthophoto", ortho_section),
    ("Seams and colour balance", seams_section),
    ("3D mesh", mesh_section),
    ("Volumes", volumes_section),
    ("Change since the earlier survey", change_section),
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


def _page(ctx: ReportContext, sections: list[str]) -> str:

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
    shown = [t for t, _ in _SECTIONS if any(f'<section id="{anchor_of(t)}">' in sec for sec in sections)]
    toc = "".join(f'<li><a href="#{anchor_of(t)}">{html.escape(t)}</a></li>' for t in shown)  # no dead link
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>geoortho quality report: {html.escape(ctx.project.name)}</title>"
        f"<style>{_CSS}</style></head><body>"
        f"<h1>Quality report: {html.escape(ctx.project.name)}</h1>"
        f'<p class="muted">geoortho {html.escape(__version__)} · project {html.escape(str(ctx.project))} · '
        f"run started {when}</p>"
        f"{banner}<nav><ol>{toc}</ol></nav>" + "\n".join(sections) + "</body></html>\n"
    )
