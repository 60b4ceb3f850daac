"""Benchmark: clean surfaces (issue 74). The DSM and DTM from the photos against the synthetic truth,
the artefacts a hillshade shows, and dem's time and memory against the code before issue 74.

For each survey (synth -> gcp-find -> sfm -> dense, cached in ``--work``), ``python -m geoortho dem
--sfm`` runs in a fresh process (start-up included), and the same with the baseline checkout
(``--baseline REF``, a git worktree made here: the ratio of the two is dem's cost of issue 74).
Printed per survey, against the truth (``geoortho.synthetic.scoring``):

* DTM RMSE, its |dZ| 95th percentile within 3 m of any object, its open-ground roughness beyond
  the truth's (the DTM less its 1 m median, RMS) in GSD;
* the DTM's RMSE where it claims ground, and where its source raster says it is a guess (under an
  object with no ground seen) with that share;
* DSM |dZ| 95th percentile within 3 m of objects, its open-ground bias in GSD;
* as dem measures itself: roughness, the step at the photos' footprint edges, the share under
  objects with no ground seen;
* dem's wall time and peak memory (and the baseline's).

    python benchmarks/bench_surface.py [--work DIR] [--baseline d36ce45] [--surveys demo,scenes]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: name -> (preset, seed, pathologies): the demo's survey and the scenes issue 74 names.
SURVEYS = {
    "demo": ("small", 0, ""),
    "scenes": ("small", 2, "wide-wood,hall,hedge,cars"),
    "breaklines": ("small", 3, "breaklines,hedge"),
}


def _run(cmd: list[str], env: dict[str, str] | None = None) -> None:
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env)


def _prepare(work: Path, name: str) -> Path:
    """The survey, its GCPs found, its SfM and dense cloud (made once)."""
    preset, seed, pathology = SURVEYS[name]
    d = work / name
    py = [sys.executable, "-m", "geoortho"]
    if not (d / "survey" / "truth" / "survey.json").is_file():
        extra = ["--pathology", pathology] if pathology else []
        _run([*py, "synth", "--output", str(d / "survey"), "--preset", preset, "--seed", str(seed), *extra])
    if not (d / "dense.laz").is_file():
        s = d / "survey"
        _run([*py, "gcp-find", "--images", str(s / "images"), "--gcp-file", str(s / "truth" / "gcp_utm.txt"),
              "--output", str(d / "gcp_list.txt")])  # fmt: skip
        _run([*py, "sfm", "--images", str(s / "images"), "--output", str(d / "sfm"), "--gcp-list",
              str(d / "gcp_list.txt"), "--max-image-size", "1024", "--max-features", "4096"])  # fmt: skip
        _run([*py, "dense", "--sfm", str(d / "sfm"), "--images", str(s / "images"), "--output", str(d / "dense.laz")])
    return d


def geoortho_timed(args: list[str], tree: str | None) -> tuple[float, float, dict[str, object]]:
    """``python -m geoortho ARGS --json`` in a fresh process: wall seconds, peak MB (the process or
    its largest worker, whichever is higher), its JSON result. ``tree``: run the package of that
    checkout (the editable install's finder, a meta path hook that would find this checkout's
    whatever PYTHONPATH says, is taken out in that process)."""
    boot = (
        "import atexit, resource, runpy, sys; "
        "atexit.register(lambda: print('PEAK_KB', max(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, "
        "resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss), file=sys.stderr)); "
        + (
            "sys.meta_path[:] = [f for f in sys.meta_path if not type(f).__module__.startswith('__editable__')]; "
            f"sys.path.insert(0, {tree!r}); "
            if tree
            else ""
        )
        + "sys.argv[0] = 'geoortho'; runpy.run_module('geoortho', run_name='__main__', alter_sys=True)"
    )
    t = time.perf_counter()
    got = subprocess.run([sys.executable, "-c", boot, *args, "--json"], check=True, capture_output=True, text=True,
                         cwd=tree or None)  # fmt: skip
    seconds = time.perf_counter() - t
    peak_kb = [float(line.split()[1]) for line in got.stderr.splitlines() if line.startswith("PEAK_KB")]
    try:
        result = json.loads(got.stdout)
    except ValueError:
        result = {}
    return seconds, (peak_kb[-1] / 1024 if peak_kb else float("nan")), result


def _dem(d: Path, out: Path, tree: str | None) -> tuple[float, float, dict[str, object]]:
    """dem --sfm in a fresh process (:func:`geoortho_timed`)."""
    out.mkdir(parents=True, exist_ok=True)
    args = ["dem", "--points", str(d / "dense.laz"), "--output", str(out / "dsm.tif"), "--dtm",
            str(out / "dtm.tif"), "--sfm", str(d / "sfm"), "--method", "idw"]  # fmt: skip
    return geoortho_timed(args, tree)


def _worktree(ref: str, into: Path) -> Path:
    root = Path(__file__).resolve().parent.parent
    subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", str(into), ref], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    return into


def bench_options(doc: str, stage: str) -> tuple[argparse.Namespace, Path, str | None]:
    """The benchmarks' shared options: the cached surveys' folder (made), and the baseline
    checkout to time ``stage`` against (a git worktree, made once), None without one."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "geoortho_bench_surface")
    ap.add_argument("--surveys", default="demo,scenes,breaklines", help=f"comma-separated, of {', '.join(SURVEYS)}")
    ap.add_argument("--baseline", default="", help=f"git ref of the code to time {stage} against (empty: none)")
    args = ap.parse_args()
    work = args.work.resolve()
    work.mkdir(parents=True, exist_ok=True)
    base_tree = None
    if args.baseline:
        base_tree = work / f"baseline-{args.baseline}"
        if not base_tree.exists():
            _worktree(args.baseline, base_tree)
    return args, work, str(base_tree) if base_tree is not None else None


def main() -> int:
    from geoortho.synthetic.scoring import score_surfaces

    args, work, base_tree = bench_options(__doc__ or "", "dem")
    rows = []
    for name in [n.strip() for n in args.surveys.split(",") if n.strip()]:
        d = _prepare(work, name)
        seconds, peak, result = _dem(d, d / "dem", None)
        s = score_surfaces(d / "survey" / "truth", d / "dem" / "dsm.tif", d / "dem" / "dtm.tif")
        row = {"survey": name, **s.as_dict(), "dem_s": seconds, "dem_peak_mb": peak}
        for k in ("dtm_roughness_m", "footprint_step_m", "dtm_under_object_share"):
            row[f"self_{k}"] = result.get(k)
        if base_tree is not None:
            b_seconds, b_peak, _ = _dem(d, d / "dem_baseline", base_tree)
            b = score_surfaces(d / "survey" / "truth", d / "dem_baseline" / "dsm.tif", d / "dem_baseline" / "dtm.tif")
            row.update({"baseline_dem_s": b_seconds, "baseline_peak_mb": b_peak, "time_ratio": seconds / b_seconds,
                        "baseline": b.as_dict()})  # fmt: skip
        rows.append(row)
        gsd = s.gsd_m
        print(f"== {name} (GSD {100 * gsd:.2f} cm)")
        print(f"  DTM RMSE {s.dtm_rmse_m:.3f} m | p95 near objects {s.dtm_p95_near_objects_m:.3f} m | "
              f"roughness excess {s.dtm_roughness_excess_gsd:.2f} GSD")  # fmt: skip
        print(f"  DTM where it claims ground: RMSE {s.dtm_rmse_claimed_m:.3f} m | where its source says a guess "
              f"(code 4): {100 * s.dtm_guess_share:.1f} % of cells, RMSE {s.dtm_guess_rmse_m:.3f} m")  # fmt: skip
        print(
            f"  DSM p95 near objects {s.dsm_p95_near_objects_m:.2f} m | open-ground bias {s.dsm_bias_open_gsd:+.2f} GSD"
        )
        print(f"  dem {seconds:.1f} s, peak {peak:.0f} MB" + (
            f" | baseline {row['baseline_dem_s']:.1f} s, {row['baseline_peak_mb']:.0f} MB: x{row['time_ratio']:.2f}; "
            f"baseline DTM RMSE {row['baseline']['dtm_rmse_m']:.3f} m, p95 near objects "
            f"{row['baseline']['dtm_p95_near_objects_m']:.3f} m; baseline DSM p95 near objects "
            f"{row['baseline']['dsm_p95_near_objects_m']:.2f} m" if base_tree is not None else ""))  # fmt: skip
    (work / "bench_surface.json").write_text(json.dumps(rows, indent=1, default=float))
    print(f"written {work / 'bench_surface.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
