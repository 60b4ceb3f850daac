"""Benchmark: what running through QGIS costs, against the plain CLI, same survey, same run.

* baseline: ``python -m geoortho footprints`` (and ``gcp-find``) straight from the shell;
* QGIS: ``qgis_process run geoortho:<id>`` with the plugin zip from tools/build_plugin.py
  installed in a throwaway profile (QGIS start, provider load from the cached registry
  description, the same CLI in a subprocess, results back as JSON);
* the provider's registry description: ``describe --json`` cold, and from its cache;
* QGIS's fixed cost: ``qgis_process help geoortho:footprints`` (start, plugins, provider).

Prints photos per second, wall seconds, the ratio QGIS / CLI, and peak RSS of the
largest child. Needs qgis_process (``make test-qgis`` installs it); says so and exits 0
without it.

    python benchmarks/bench_qgis.py [--preset tiny|small] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(PROJECT))


def _timed(cmd: list[str], env: dict[str, str]) -> float:
    t0 = time.perf_counter()
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"{' '.join(cmd[:4])} failed: {(r.stderr or r.stdout)[-800:]}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="small", choices=("tiny", "small"))
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if shutil.which("qgis_process") is None:
        print("bench_qgis: qgis_process not found (make test-qgis installs QGIS); nothing measured")
        return

    from geoortho.qgis_provider.interpreter import load_description
    from geoortho.synthetic.survey import synth

    work = Path(tempfile.mkdtemp(prefix="bench-qgis-"))
    survey = synth(work / "survey", preset=args.preset, seed=1)
    profile = work / "profile"
    subprocess.run(
        [sys.executable, str(PROJECT / "tools" / "build_plugin.py"), str(work / "p.zip")],
        check=True,
        capture_output=True,
    )
    with zipfile.ZipFile(work / "p.zip") as z:
        z.extractall(profile / "profiles" / "default" / "python" / "plugins")
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "QGIS_PLUGINPATH")}
    env.update(
        QT_QPA_PLATFORM="offscreen",
        QGIS_CUSTOM_CONFIG_PATH=str(profile),
        GEOORTHO_PYTHON=sys.executable,
        XDG_RUNTIME_DIR=str(work),
    )
    subprocess.run(["qgis_process", "plugins", "enable", "geoortho_qgis"], env=env, check=True, capture_output=True)

    t0 = time.perf_counter()
    load_description(sys.executable, work / "cache.json")
    cold = time.perf_counter() - t0
    t0 = time.perf_counter()
    load_description(sys.executable, work / "cache.json")
    cached = time.perf_counter() - t0
    print(f"registry description: cold {cold:.2f} s, cached {cached * 1000:.1f} ms ({cold / cached:.0f}x)")

    startup = min(_timed(["qgis_process", "help", "geoortho:footprints"], env) for _ in range(args.repeat))
    print(f"qgis_process start with the provider loaded (help geoortho:footprints): {startup:.2f} s")

    gcp = survey.truth / "gcp_wgs84.csv"
    jobs = {
        "footprints": (["--images", str(survey.images), "--output"], "out.gpkg"),
        "gcp-find": (["--images", str(survey.images), "--gcp-file", str(gcp), "--output"], "gcp_list.txt"),
    }
    print(f"{survey.n_photos} photos ({args.preset}), best of {args.repeat}")
    print(f"{'algorithm':<12} {'CLI s':>7} {'QGIS s':>7} {'photos/s CLI':>13} {'photos/s QGIS':>14} {'ratio':>6}")
    for alg, (cli_args, name) in jobs.items():
        cli, qgis = [], []
        for i in range(args.repeat):
            out = work / f"{alg}-{i}-{name}"
            cli.append(_timed([sys.executable, "-m", "geoortho", alg, *cli_args, str(out), "--quiet"], env))
            qgis_args = [f"--{a[2:].replace('-', '_').upper()}={b}" for a, b in zip(cli_args[::2], cli_args[1::2])]
            qgis.append(
                _timed(
                    ["qgis_process", "run", f"geoortho:{alg}", *qgis_args, f"--OUTPUT={work / f'q-{alg}-{i}-{name}'}"],
                    env,
                )
            )
        c, q = min(cli), min(qgis)
        n = survey.n_photos
        print(f"{alg:<12} {c:7.2f} {q:7.2f} {n / c:13.2f} {n / q:14.2f} {q / c:6.2f}")
    kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    print(f"peak RSS of the largest child: {kb / 1024:.0f} MB")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
