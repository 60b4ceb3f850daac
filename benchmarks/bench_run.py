"""Benchmark: ``run`` against its stages run one by one, same survey, same run.

Makes (or takes) a synthetic survey, then in child processes:

1. ``geoortho run`` (GCP file, every third GCP a checkpoint, the demo's sfm options): wall time,
   peak memory, each stage's seconds (run.json) and the pipeline's own time (hashing, ledger);
2. each stage alone, ``geoortho <stage>`` with exactly the values run.json recorded for it,
   into a separate folder: the plain baseline (target: run <= 1.1 x their sum);
3. ``geoortho run`` again, nothing changed (target: < 5 % of the first);
4. ``geoortho run`` with one ortho option changed: which stages were re-done (only ortho, report).

    python benchmarks/bench_run.py [--preset small|medium] [--survey DIR]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from bench_sfm import OURS, _child

STAGE_OPTIONS = {"sfm": {"max_image_size": 1024, "max_features": 4096}}


def _geoortho(*args: str) -> tuple[float, int]:
    dt, _, peak_kb = _child(OURS, ["geoortho", *args, "--quiet"])
    return dt, peak_kb


def _cli_args(values: dict, project: Path, alone: Path) -> list[str]:
    """run.json's values of a stage as CLI options, with the project's paths moved to ``alone``."""
    out = []
    for k, v in values.items():
        if isinstance(v, str) and v.startswith("PROJECT/"):
            v = str(alone / v[len("PROJECT/") :])
        out += ["--" + k.replace("_", "-"), str(v)]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--survey", type=Path, help="an existing synth output folder")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="bench_run_"))
    survey = args.survey or work / "survey"
    if args.survey is None:
        _geoortho("synth", "--output", str(survey), "--preset", args.preset, "--seed", "1")
    images = survey / "images"
    gcps = survey / "truth" / "gcp_utm.txt"
    names = sorted(ln.split()[0] for ln in gcps.read_text().splitlines()[1:] if ln.strip())
    project = work / "project"
    run_args = ["run", "--images", str(images), "--output", str(project), "--gcp-file", str(gcps),
                "--checkpoints", ",".join(names[::3]), "--stage-options", json.dumps(STAGE_OPTIONS)]  # fmt: skip
    t_run, rss_run = _geoortho(*run_args)
    ledger = json.loads((project / "run.json").read_text())
    stages = {n: r for n, r in ledger["stages"].items() if r.get("status") == "done"}
    n_photos = len(list(images.glob("*.JPG")))
    print(f"run on {args.preset} ({n_photos} photos): {t_run:.1f} s, peak {rss_run / 1024:.0f} MB")
    print(f"  {'stage':<11} {'in run (s)':>10} {'alone (s)':>10} {'peak MB in run':>15}")
    alone_total = 0.0
    alone = work / "alone"
    for name, rec in stages.items():
        if name == "report":
            t_alone, _ = _geoortho("report", "--project", str(project), "--output", str(work / "report_alone.html"))
        else:
            (alone / name).mkdir(parents=True, exist_ok=True)
            t_alone, _ = _geoortho(name, *_cli_args(rec["values"], project, alone))
        alone_total += t_alone
        peak = rec.get("peak_memory_mb", {}).get("with_workers", 0)
        print(f"  {name:<11} {rec['seconds']:>10.1f} {t_alone:>10.1f} {peak:>15.0f}")
    last = ledger["runs"][-1]
    print(f"run / stages one by one: {t_run:.1f} / {alone_total:.1f} s = {t_run / alone_total:.3f} (target <= 1.1)")
    print(
        f"pipeline's own time (hashing, fingerprints, ledger): {last['overhead_seconds']:.2f} s "
        f"= {100 * last['overhead_seconds'] / last['seconds']:.2f} % of the run (target < 2 %)"
    )
    t_again, _ = _geoortho(*run_args)
    print(f"second run, nothing changed: {t_again:.1f} s = {100 * t_again / t_run:.1f} % of the first (target < 5 %)")
    changed = json.dumps({**STAGE_OPTIONS, "ortho": {"resolution_m": 0.05}})
    t0 = time.perf_counter()
    _geoortho(*run_args[:-1], changed)
    t_changed = time.perf_counter() - t0
    redone = [n for n, s in json.loads((project / "run.json").read_text())["runs"][-1]["stages"].items() if s == "ran"]
    print(f"ortho option changed: {t_changed:.1f} s, re-done: {', '.join(redone)} (target: ortho, report)")


if __name__ == "__main__":
    main()
