"""Benchmark: how each stage grows with the survey — time and peak memory per stage per size.

Synthetic surveys of increasing size (the ``small`` scene widened, photos at a small image
size so that hundreds render in minutes) go through footprints, gcp-find, sfm (spatial matching;
split-merge at the largest size), dense, dem and ortho, each as ``python -m geoortho`` in a child
process whose peak memory is its own (VmHWM; its pool workers, one per core, are processes of
their own and not counted: this is the coordinating process's growth). Printed: a table of seconds and MB per stage and
size, then per stage the exponent b of time ∝ photos^b fitted over the sizes (target: b ≲ 1.1,
every stage about linear) and the memory growth from the smallest size to the largest (target:
flat for the per-photo and per-tile stages). For sfm, the same per step (features, matching,
mapping, the lens test, georeferencing) from its report, where incremental mapping spent its time, and the
cameras and checkpoints (every fourth GCP held out) against the truth, in GSD.

The first figure is the render rate of the survey itself (photos per minute and megapixels per
second on every core, and the minutes 1,000 photos would take at that rate): a large survey is
only a benchmark input if it renders well within the hour.

With ``--keep DIR`` the surveys and every stage's products stay in DIR and each stage's figures
are recorded beside them (``DIR/sN/times-*.json``): a later run with the same DIR renders no survey
again and runs only the stages not yet recorded, so a 1,000-photo survey can be measured a stage at a
time. The products of a split and an unsplit sfm go to separate folders (``out`` and ``out-splitN``).
CPU seconds (the child's and its pool workers') are printed beside the wall time: on a busy machine
they say how much of the wall time was the stage's own.

    python benchmarks/bench_scale.py [--photos 100,300,1000] [--image-px 1600] [--split 150]
        [--stages footprints,gcp-find,sfm,dense,dem,ortho] [--scheduler ADDRESS] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import shutil
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from bench_sfm import OURS, child_with_tree

SFM_STEPS = ("features", "matching", "mapping", "lens_distortion_test", "georeferencing")
STAGES = ("footprints", "gcp-find", "sfm", "dense", "dem", "ortho")
#: 4x4 markers as the presets' DICT_4X4_50, with ids enough for the GCPs and decoys of a wide survey
DICTIONARY = "DICT_4X4_250"


def scale_preset(n_photos: int, image_px: int) -> Any:
    """The small preset widened until its flight plan holds at least ``n_photos`` photos (same
    altitude and overlaps; buildings and trees in proportion to the area)."""
    from types import SimpleNamespace

    from geoortho.synthetic import survey as synthetic

    base = synthetic.PRESETS["small"]

    def widened(k: float) -> Any:
        return replace(
            base,
            name=f"scale{n_photos}",
            area_m=(base.area_m[0] * k, base.area_m[1] * k),
            image_px=(image_px, round(image_px * 2 / 3)),
            n_buildings=max(1, round(base.n_buildings * k * k)),
            n_trees=max(1, round(base.n_trees * k * k)),
            n_markers=max(4, round(base.n_markers * k)),
            points_per_m2=4.0,
        )

    def planned(k: float) -> int:
        p = widened(k)
        aw, ah = p.area_m
        box = SimpleNamespace(flight_box=(-aw / 2, -ah / 2, aw / 2, ah / 2), home=(0.0, 0.0, 0.0))
        return len(synthetic.plan_flight(p, box, np.random.default_rng(0)))  # type: ignore[arg-type]

    # the photos grow with the area less their edge lines: the smallest widening that holds enough
    lo, hi = 0.5, 2.0 * math.sqrt(max(n_photos, 1) / 35.0) + 1.0  # the small preset flies 35 photos
    for _ in range(30):
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if planned(mid) >= n_photos else (mid, hi)
    return widened(hi)


def make_survey(folder: Path, n_photos: int, image_px: int, seed: int = 0) -> tuple[Path, int]:
    """The small scene widened to at least ``n_photos`` photos (see :func:`scale_preset`)."""
    from geoortho.synthetic import survey as synthetic

    preset = scale_preset(n_photos, image_px)
    name = preset.name
    synthetic.PRESETS[name] = preset
    r = synthetic.synth(folder, preset=name, seed=seed, dictionary=DICTIONARY)  # type: ignore[arg-type]
    return folder, r.n_photos


def stage_argv(
    survey: Path, out: Path, sfm_options: list[str], ortho_dsm: Path, dictionary: str | None = None
) -> dict[str, list[str]]:
    """Each stage's ``geoortho`` arguments on a synth survey, chained through ``out``."""
    img, gcp = survey / "images", survey / "truth" / "gcp_utm.txt"
    argv = {
        "footprints": ["footprints", "--images", img, "--output", out / "fp.gpkg", "--dsm", survey / "truth/dsm.tif"],
        "gcp-find": ["gcp-find", "--images", img, "--gcp-file", gcp, "--output", out / "gcp_list.txt"]
        + (["--dictionary", dictionary] if dictionary else []),
        "sfm": ["sfm", "--images", img, "--output", out / "sfm", "--gcp-list", out / "gcp_list.txt", *sfm_options],
        "dense": ["dense", "--sfm", out / "sfm", "--images", img, "--output", out / "dense.laz"],
        "dem": ["dem", "--points", out / "dense.laz", "--output", out / "dsm.tif", "--dtm", out / "dtm.tif"],
        "ortho": ["ortho", "--images", img, "--output", out / "ortho.tif", "--sfm", out / "sfm", "--dsm", ortho_dsm],
    }
    return {stage: [str(a) for a in args] for stage, args in argv.items()}


def checkpoints(gcp_file: Path) -> list[str]:
    """Every fourth GCP of the survey's file, held out of the adjustment and measured."""
    from geoortho.gcp.io import read_gcp_file

    return [p.name for p in read_gcp_file(gcp_file).points][::4]


def against_truth(report: dict, cameras_gpkg: Path, poses_json: Path) -> str:
    """The registered cameras' and the checkpoints' errors against the synthetic truth, in GSD."""
    import geopandas as gpd

    gsd_m = report["gsd_cm"] / 100.0
    cams = gpd.read_file(cameras_gpkg, layer="cameras")
    cams = cams[cams["registered"].astype(bool)].set_index("image")
    truth = {p["image"]: p for p in json.loads(poses_json.read_text())}
    names = [n for n in cams.index if n in truth]
    e = np.array([[cams.at[n, k] - truth[n][k] for k in ("x", "y", "z")] for n in names])
    h = float(np.sqrt((e[:, 0] ** 2 + e[:, 1] ** 2).mean()))
    v = float(np.sqrt((e[:, 2] ** 2).mean()))
    chk = report.get("checkpoint_accuracy") or {}
    chk_txt = (
        f"checkpoints ({chk['n']}): {chk['rmse_horizontal_m'] / gsd_m:.2f} GSD h, {chk['rmse_z_m'] / gsd_m:.2f} GSD v"
        if chk.get("n")
        else "no checkpoint measured"
    )
    return (
        f"cameras against the truth ({len(names)}): {h / gsd_m:.2f} GSD h, {v / gsd_m:.2f} GSD v "
        f"(GSD {gsd_m * 100:.2f} cm; target <= 1.5 GSD h with GCPs); {chk_txt}"
    )


def run(argv: list[str], scheduler: str | None) -> tuple[float, float, float, float]:
    """Seconds, the main process's peak MB, CPU seconds (with its pool workers) and the peak MB of
    the whole process tree (the main process and its pool workers together, sampled) of one
    ``python -m geoortho`` run."""
    if scheduler:
        argv = [*argv, "--scheduler", scheduler]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    dt, _, peak_kb, tree_peak_mb = child_with_tree(OURS, ["geoortho", *argv])
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_s = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return dt, peak_kb / 1024, cpu_s, max(tree_peak_mb, peak_kb / 1024)


def survey_in(folder: Path, want: int, image_px: int) -> int:
    """The survey of at least ``want`` photos in ``folder``: rendered (and its rate printed), or reused."""
    made = folder / "truth" / "markers.json"  # written once every photo is rendered
    n = sum(1 for p in (folder / "images").iterdir() if p.suffix.lower() == ".jpg") if made.is_file() else 0
    if n >= want:
        print(f"survey of {n} photos reused from {folder}", flush=True)
        return n
    if folder.exists():  # a render cut short, or a smaller survey
        shutil.rmtree(folder)
    t = time.perf_counter()
    _, n = make_survey(folder, want, image_px)
    dt = time.perf_counter() - t
    mp = image_px * round(image_px * 2 / 3) / 1e6
    print(
        f"survey of {n} photos ({image_px} px wide, {mp:.1f} MP) rendered in {dt:.0f} s: "
        f"{60 * n / dt:.1f} photos/min, {n * mp / dt:.2f} MP/s; 1,000 photos at this rate: "
        f"{1000 * dt / n / 60:.0f} min",
        flush=True,
    )
    return n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", default="100,300,1000")
    ap.add_argument("--image-px", type=int, default=1600, help="photo width (1600: 1.7 MP)")
    ap.add_argument("--split", type=int, default=150, help="sfm split-merge for surveys above this many photos")
    ap.add_argument("--stages", default=",".join(STAGES))
    ap.add_argument("--scheduler", default=None, help="a Dask scheduler for every stage")
    ap.add_argument("--keep", default=None, help="keep surveys, products and figures here; rerun only what is missing")
    args = ap.parse_args()
    stages = [s for s in args.stages.split(",") if s]
    table: dict[str, dict[int, tuple[float, float]]] = {s: {} for s in stages}
    sfm_steps: dict[str, dict[int, float]] = {}
    sizes = []
    tree_peak: dict[int, float] = {}  # the largest whole-tree memory of any stage, per size
    with tempfile.TemporaryDirectory() as temporary:
        d = Path(args.keep) if args.keep else Path(temporary)
        for want in (int(x) for x in args.photos.split(",")):
            s = d / f"s{want}"
            n = survey_in(s, want, args.image_px)
            sizes.append(n)
            gcp = s / "truth" / "gcp_utm.txt"
            split = n > args.split
            out = s / (f"out-split{args.split}" if split else "out")
            sfm_options = ["--checkpoints", ",".join(checkpoints(gcp))]
            sfm_options += ["--max-image-size", str(args.image_px), "--matching", "spatial"]
            sfm_options += ["--split", str(args.split)] if split else []
            argv = stage_argv(s, out, sfm_options, out / "dsm.tif", DICTIONARY)
            out.mkdir(parents=True, exist_ok=True)
            record = out / "times.json"
            times = json.loads(record.read_text()) if record.is_file() else {}
            for st in stages:
                if st in times:
                    dt, mb, cpu, *tree = times[st]  # (figures recorded before the tree was sampled: none)
                    tree_mb = tree[0] if tree else mb
                    note = " (recorded)"
                else:
                    dt, mb, cpu, tree_mb = run([*argv[st], "--quiet"], args.scheduler)
                    times[st] = (dt, mb, cpu, tree_mb)
                    if args.keep:
                        record.write_text(json.dumps(times, indent=1))
                    note = ""
                table[st][n] = (dt, mb)
                tree_peak[n] = max(tree_peak.get(n, 0.0), tree_mb)
                print(
                    f"  {st:10s} {n:5d} photos: {dt:7.1f} s  {mb:7.0f} MB main, {tree_mb:7.0f} MB with workers  "
                    f"cpu {cpu:7.1f} s  "
                    f"({n / dt:.2f} photos/s){note}",
                    flush=True,
                )
                if st == "sfm":
                    report = json.loads((out / "sfm" / "report.json").read_text())
                    for step, sec in report["seconds"].items():
                        if step in SFM_STEPS:
                            sfm_steps.setdefault(step, {})[n] = float(sec)
                    print("    " + ", ".join(f"{k} {v:.1f} s" for k, v in report["seconds"].items()), flush=True)
                    print("    mapping profile: " + json.dumps(report.get("mapping_profile", {})), flush=True)
                    truth = against_truth(report, out / "sfm" / "cameras.gpkg", s / "truth" / "poses.json")
                    print("    " + truth, flush=True)
    print("\nstage       " + "".join(f"{n:>16d}" for n in sizes) + "   time exponent   memory x (last/first)")
    for st in stages:
        row = table[st]
        ns = np.array(sorted(row))
        ts = np.array([row[n][0] for n in ns])
        ms = np.array([row[n][1] for n in ns])
        b = float(np.polyfit(np.log(ns), np.log(ts), 1)[0]) if len(ns) >= 2 else math.nan
        cells = "".join(f"{row[n][0]:8.1f}s{row[n][1]:6.0f}MB" for n in ns)
        print(f"{st:10s}  {cells}   {b:8.2f}        x{ms[-1] / ms[0]:.2f}")
    for step, row in sfm_steps.items():
        ns = np.array(sorted(row))
        ts = np.array([max(row[n], 1e-3) for n in ns])
        b = float(np.polyfit(np.log(ns), np.log(ts), 1)[0]) if len(ns) >= 2 else math.nan
        print(f"  sfm {step:14s}" + "".join(f"{row[n]:15.1f}s " for n in ns) + f"  {b:8.2f}")
    print(
        "peak memory of the largest stage with its workers: "
        + ", ".join(f"{n} photos {mb / 1024:.2f} GB" for n, mb in sorted(tree_peak.items()))
        + " (target: <= 8 GB at 1,000 photos)"
    )
    print("(target: time exponent <= ~1.1 for every stage; memory flat for per-photo and per-tile stages)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
