"""Benchmark: geoortho sfm against pycolmap's stages called directly, same photos, same run.

Each side runs in its own child process (so peak memory is its own):

* raw pycolmap: import_images (one camera), extract_features, match_exhaustive
  or match_spatial (COLMAP's own GPS priors from EXIF), incremental_mapping;
  the same SIFT settings as geoortho's;
* geoortho: ``python -m geoortho sfm`` (metadata, per-body cameras, GPS priors
  in the output CRS, mapping with prior-weighted bundle adjustment,
  georeferencing, LAZ/GeoPackage/report writing).

Prints wall time per stage and peak RSS of each, and geoortho's overhead over
raw pycolmap (target <= 10 %).

    python benchmarks/bench_sfm.py [--preset small|medium] [--survey DIR] [--max-image-size 1024]

``--mappers`` instead runs geoortho's sfm twice on the same photos, with the incremental and the
global (GLOMAP) mapper, and prints time per stage, registration, reprojection, model tilt, focal
drift and GPS residuals of each (``--images DIR`` for real photos, e.g. ../shared/data/real/toledo_dji/images;
target: a 75-photo 12 MP block in <= 10 min on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

RAW = r"""
import json, resource, sys, time
import pycolmap
from pathlib import Path
images, work, size, feats, how, dist = json.loads(sys.argv[1])
work = Path(work); work.mkdir(parents=True, exist_ok=True)
db = work / "database.db"
pycolmap.Database.open(db).close()
t = {}
t0 = time.perf_counter()
names = sorted(p.name for p in Path(images).iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
pycolmap.import_images(db, images, pycolmap.CameraMode.SINGLE, names)
eo = pycolmap.FeatureExtractionOptions()
eo.max_image_size = size; eo.sift.max_num_features = feats; eo.sift.first_octave = 0
pycolmap.extract_features(db, images, names, extraction_options=eo)
t["features"] = time.perf_counter() - t0
t0 = time.perf_counter()
if how == "spatial":
    po = pycolmap.SpatialPairingOptions(); po.max_distance = dist; po.max_num_neighbors = 30
    pycolmap.match_spatial(db, pairing_options=po)
else:
    pycolmap.match_exhaustive(db)
t["matching"] = time.perf_counter() - t0
t0 = time.perf_counter()
o = pycolmap.IncrementalPipelineOptions(); o.min_model_size = 3; o.random_seed = 0
recs = pycolmap.incremental_mapping(db, images, work / "sparse", o)
t["mapping"] = time.perf_counter() - t0
best = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None
t["registered"] = best.num_reg_images() if best else 0
print(json.dumps(t))
# VmHWM, not ru_maxrss: a child inherits its parent's ru_maxrss across fork and exec
print("peak_rss_kb", next(int(s.split()[1]) for s in open("/proc/self/status") if s[:6] == "VmHWM:"), file=sys.stderr)
"""

# The CLI in a child that reports its own peak memory on its last stderr line. Arguments
# "set:module.NAME=INT" before the algorithm set a module constant first (bench_dem: tiles or not).
OURS = r"""
import importlib, json, resource, runpy, sys
sys.argv = json.loads(sys.argv[1])
while len(sys.argv) > 1 and sys.argv[1].startswith("set:"):
    target, value = sys.argv.pop(1)[4:].split("=")
    module, name = target.rsplit(".", 1)
    setattr(importlib.import_module(module), name, int(value))
try:
    runpy.run_module("geoortho", run_name="__main__")
finally:
    # VmHWM, not ru_maxrss: a child inherits its parent's ru_maxrss across fork and exec
    hwm = next(int(s.split()[1]) for s in open("/proc/self/status") if s[:6] == "VmHWM:")
    print("peak_rss_kb", hwm, file=sys.stderr)
"""


def _tree_rss_mb(root: int) -> float:
    """The summed resident memory of ``root`` and every process under it (Linux /proc)."""
    total, todo = 0.0, [root]
    while todo:
        pid = todo.pop()
        try:
            total += next(int(x.split()[1]) for x in open(f"/proc/{pid}/status") if x.startswith("VmRSS:")) / 1024
            for task in Path(f"/proc/{pid}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
        except (OSError, StopIteration, ValueError):
            continue  # the process ended as it was read
    return total


def child_with_tree(code: str, args: list) -> tuple[float, str, int, float]:
    """Run ``code`` in a child: seconds, its stdout, its own peak KB (its last stderr line) and the
    peak MB of its whole process tree (it and its pool workers, sampled each 0.5 s)."""
    t = time.perf_counter()
    proc = subprocess.Popen(
        [sys.executable, "-c", code, json.dumps(args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    tree_peak_mb = 0.0
    done = threading.Event()

    def sample() -> None:
        nonlocal tree_peak_mb
        while not done.wait(0.5):
            tree_peak_mb = max(tree_peak_mb, _tree_rss_mb(proc.pid))

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    out, err = proc.communicate()
    done.set()
    sampler.join()
    dt = time.perf_counter() - t
    if proc.returncode:
        sys.stderr.write(err[-3000:])
        raise SystemExit(1)
    peak_kb = int(err.strip().splitlines()[-1].split()[-1])
    return dt, out, peak_kb, tree_peak_mb


def _child(code: str, args: list) -> tuple[float, str, int]:
    dt, out, peak_kb, _ = child_with_tree(code, args)
    return dt, out, peak_kb


def compare_mappers(images: Path, max_image_size: int, max_features: int) -> None:
    """geoortho sfm with each mapper on the same photos: time per stage and what came out."""
    n = sum(1 for p in images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
    rows = {}
    with tempfile.TemporaryDirectory() as d:
        for mapper in ("incremental", "global"):
            out = Path(d) / mapper
            argv = [
                "geoortho",
                "sfm",
                "--images",
                str(images),
                "--output",
                str(out),
                "--mapper",
                mapper,
                "--max-image-size",
                str(max_image_size),
                "--max-features",
                str(max_features),
                "--json",
                "--quiet",
            ]
            wall, _, peak = _child(OURS, argv)
            rows[mapper] = (wall, peak, json.loads((out / "report.json").read_text()))
    print(f"{n} photos, SIFT at {max_image_size} px / {max_features} features")
    print(f"{'':<26}{'incremental':>14}{'global':>14}")
    for k in ("metadata", "features", "matching", "mapping", "georeferencing", "outputs"):
        print(f"{k + ' s':<26}" + "".join(f"{r[2]['seconds'].get(k, 0):>14.1f}" for r in rows.values()))
    print(f"{'wall s':<26}" + "".join(f"{r[0]:>14.1f}" for r in rows.values()))
    print(f"{'peak RSS MB':<26}" + "".join(f"{r[1] / 1024:>14.0f}" for r in rows.values()))
    print(f"{'registered':<26}" + "".join(f"{r[2]['registered']:>14d}" for r in rows.values()))
    print(f"{'reprojection px':<26}" + "".join(f"{r[2]['mean_reprojection_error_px']:>14.2f}" for r in rows.values()))
    print(
        f"{'model tilt deg':<26}" + "".join(f"{(r[2]['model_tilt_deg'] or float('nan')):>14.2f}" for r in rows.values())
    )
    print(
        f"{'focal drift % (1st cam)':<26}"
        + "".join(f"{(r[2]['intrinsics'][0]['focal_drift_pct'] or 0):>14.2f}" for r in rows.values())
    )
    print(
        f"{'GPS RMSE E/N/Z m':<26}"
        + "".join(
            "{:>14}".format("/".join(f"{v:.1f}" for v in r[2]["gps"]["rmse_m"])) if r[2]["gps"] else f"{'-':>14}"
            for r in rows.values()
        )
    )
    # where incremental mapping spent its time (the report's profile; the global mapper has none)
    for key, label in (
        ("tracks_per_photo_median", "tracks per photo (median)"),
        ("points", "3D points"),
        ("registration_steps", "registration steps"),
        ("median_step_s", "median step s"),
        ("adjustment_steps", "whole-model adjustments"),
        ("adjustment_s", "adjustments beyond a step s"),
    ):
        print(f"{label:<26}" + "".join(f"{r[2].get('mapping_profile', {}).get(key, '-'):>14}" for r in rows.values()))
    inc, glo = rows["incremental"][0], rows["global"][0]
    print(
        f"global / incremental wall time: {glo / inc:.2f}; per photo {inc / n:.1f} s vs {glo / n:.1f} s; "
        f"75 photos at this rate: {75 * min(inc, glo) / n / 60:.1f} min (target <= 10 min)"
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--survey", type=Path, help="an existing synth folder (skips making one)")
    ap.add_argument("--images", type=Path, help="a folder of photos (with --mappers)")
    ap.add_argument("--mappers", action="store_true", help="compare the incremental and global mappers")
    ap.add_argument("--max-image-size", type=int, default=1024)
    ap.add_argument("--max-features", type=int, default=4096)
    args = ap.parse_args()
    if args.mappers:
        images = args.images or (args.survey / "images" if args.survey else None)
        if images is None:
            ap.error("--mappers needs --images or --survey")
        compare_mappers(images, args.max_image_size, args.max_features)
        return 0
    with tempfile.TemporaryDirectory() as d:
        survey = args.survey
        if survey is None:
            from geoortho.synthetic.survey import synth

            survey = synth(Path(d) / "survey", preset=args.preset).output
        images = survey / "images"
        n = sum(1 for p in images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))
        # ours first: its report says which matcher and radius "auto" chose; raw uses the same
        argv = [
            "geoortho",
            "sfm",
            "--images",
            str(images),
            "--output",
            str(Path(d) / "ours"),
            "--max-image-size",
            str(args.max_image_size),
            "--max-features",
            str(args.max_features),
            "--json",
            "--quiet",
        ]
        t_ours, out, peak_ours = _child(OURS, argv)
        rep = json.loads((Path(d) / "ours" / "report.json").read_text())
        how = rep["matching"].split()[0]
        dist = float(rep["matching"].split("within ")[1].split()[0]) if how == "spatial" else 0.0
        t_raw, out_raw, peak_raw = _child(
            RAW, [str(images), str(Path(d) / "raw"), args.max_image_size, args.max_features, how, dist]
        )
        raw = json.loads(out_raw.strip().splitlines()[-1])
        s = rep["seconds"]
        print(f"{n} photos, SIFT at {args.max_image_size} px / {args.max_features} features, matching {how}")
        print(f"{'stage':<16}{'pycolmap':>10}{'geoortho':>10}")
        for k in ("features", "matching", "mapping"):
            print(f"{k:<16}{raw[k]:>9.1f}s{s.get(k, 0):>9.1f}s")
        extra = {k: v for k, v in s.items() if k not in ("features", "matching", "mapping", "total")}
        print("geoortho only: " + ", ".join(f"{k} {v:.2f} s" for k, v in extra.items()))
        print(f"{'wall (process)':<16}{t_raw:>9.1f}s{t_ours:>9.1f}s")
        print(f"registered: pycolmap {raw['registered']}/{n}, geoortho {rep['registered']}/{n}")
        print(f"peak RSS: pycolmap {peak_raw / 1024:.0f} MB, geoortho {peak_ours / 1024:.0f} MB")
        print(
            f"geoortho overhead over raw pycolmap: {100 * (t_ours - t_raw) / t_raw:+.1f} % "
            f"(target <= 10 %); georeferenced by {rep['georeferenced_by']}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
