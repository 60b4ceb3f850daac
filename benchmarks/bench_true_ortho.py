"""Benchmark: a true orthophoto (issue 75). ``ortho`` on the photos' own SfM and DSM, against the
synthetic survey's true orthophoto, and its time and memory against an earlier checkout.

For each survey of ``bench_surface.py`` (synth -> gcp-find -> sfm -> dense -> dem, cached in
``--work``; dem is run here when its DSM is missing), ``python -m geoortho ortho`` runs in a fresh
process (start-up included), and with ``--baseline REF`` the same with that checkout (a git
worktree made here). Printed per survey, against the truth (``geoortho.synthetic.scoring``):

* structural similarity (grey, the ortho's gain and offset fitted) on open ground and within 3 m
  of any object;
* the roof-edge position error: per 0.5 m piece of each building's true outline, where the
  ortho's gradient is strongest within 1 m of it; the median in GSD (and the same measure on the
  true orthophoto, its floor);
* the transparent area inside what two photos saw; the seam colour step after balancing;
* ortho's wall time and peak memory (and the baseline's).

    python benchmarks/bench_true_ortho.py [--work DIR] [--baseline REF] [--surveys demo,scenes]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_surface import _dem, _prepare, bench_options, geoortho_timed  # noqa: E402


def _ortho(d: Path, out: Path, tree: str | None) -> tuple[float, float, dict[str, object]]:
    out.mkdir(parents=True, exist_ok=True)
    args = ["ortho", "--images", str(d / "survey" / "images"), "--sfm", str(d / "sfm"), "--dsm",
            str(d / "dem" / "dsm.tif"), "--output", str(out / "ortho.tif"), "--workers", "2"]  # fmt: skip
    return geoortho_timed(args, tree)


def main() -> int:
    from geoortho.synthetic.scoring import score_ortho

    args, work, base_tree = bench_options(__doc__ or "", "ortho")
    rows = []
    for name in [n.strip() for n in args.surveys.split(",") if n.strip()]:
        d = _prepare(work, name)
        if not (d / "dem" / "dsm.tif").is_file():
            _dem(d, d / "dem", None)
        seconds, peak, result = _ortho(d, d / "ortho", None)
        s = score_ortho(d / "survey" / "truth", d / "ortho" / "ortho.tif")
        row = {"survey": name, **s.as_dict(), "ortho_s": seconds, "ortho_peak_mb": peak,
               "seam_step_dn": result.get("seam_mismatch_balanced")}  # fmt: skip
        if base_tree is not None:
            b_seconds, b_peak, _ = _ortho(d, d / "ortho_baseline", base_tree)
            b = score_ortho(d / "survey" / "truth", d / "ortho_baseline" / "ortho.tif")
            row.update({"baseline_ortho_s": b_seconds, "baseline_peak_mb": b_peak, "time_ratio": seconds / b_seconds,
                        "baseline": b.as_dict()})  # fmt: skip
        rows.append(row)
        print(f"== {name} (GSD {100 * s.gsd_m:.2f} cm)")
        print(f"  SSIM open ground {s.ssim_open:.3f} | within 3 m of objects {s.ssim_near_objects:.3f}")
        print(f"  roof edges {s.roof_edge_error_gsd:.2f} GSD (median of the {s.roof_edge_pieces} pieces the true "
              f"ortho shows its edge on; {s.roof_edge_error_all_gsd:.2f} over every piece, the true ortho's own "
              f"{s.roof_edge_error_truth_gsd:.2f}) | holes {s.holes_inside_m2:.2f} m2 | seam step "
              f"{row['seam_step_dn']} DN")  # fmt: skip
        line = f"  ortho {seconds:.1f} s, peak {peak:.0f} MB"
        if base_tree is not None:
            b = row["baseline"]
            line += (f" | baseline {row['baseline_ortho_s']:.1f} s, {row['baseline_peak_mb']:.0f} MB: "
                     f"x{row['time_ratio']:.2f}; baseline SSIM near objects {b['ssim_near_objects']:.3f}, roof edges "
                     f"{b['roof_edge_error_gsd']:.2f} GSD")  # fmt: skip
        print(line)
    (work / "bench_true_ortho.json").write_text(json.dumps(rows, indent=1, default=float))
    print(f"written {work / 'bench_true_ortho.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
