"""Benchmark: the textured mesh (glTF + 3D Tiles) against the orthophoto on the same survey.

Each command runs as a user meets it, a fresh ``python -m geoortho`` process with its start-up:
``ortho`` (the baseline the issue names: the mesh should take no longer) and ``mesh`` from the
same DSM and that orthophoto. Prints both times and their ratio, the peak memory of each process
tree, faces and MB per hectare, the tiles, and the mesh's error against the DSM.

    python benchmarks/bench_mesh.py --project demo_output/project     # a run's project (DSM, sfm, photos)
    python benchmarks/bench_mesh.py                                    # makes the tiny survey's run first
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from bench_sfm import OURS, child_with_tree


def _project(args: argparse.Namespace, scratch: Path) -> Path:
    if args.project is not None:
        return Path(args.project)
    import geoortho

    survey = geoortho.synth(scratch / "survey", preset=args.preset, seed=1)
    geoortho.run(survey.images, scratch / "project", gcp_file=survey.gcp_file,
                 stage_options={"sfm": {"max_image_size": 1024}, "dense": {"max_image_size": 512}})  # fmt: skip
    return scratch / "project"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--project", type=Path, default=None, help="a run's project folder (default: make one)")
    ap.add_argument("--preset", default="tiny", help="the survey made when no project is given")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        scratch = Path(d)
        project = _project(args, scratch)
        ledger = json.loads((project / "run.json").read_text())
        images = Path(ledger["stages"]["ortho"]["values"]["images"])
        dsm = project / "dem" / "dsm.tif"
        ortho_args = ["geoortho", "ortho", "--images", str(images), "--sfm", str(project / "sfm"), "--dsm", str(dsm),
                      "--output", str(scratch / "ortho.tif"), "--quiet", "--json"]  # fmt: skip
        t_ortho, _, _, mb_ortho = child_with_tree(OURS, ortho_args)
        # as run makes it: its walls coloured from the photos
        mesh_args = ["geoortho", "mesh", "--dsm", str(dsm), "--ortho", str(scratch / "ortho.tif"), "--output",
                     str(scratch / "mesh.glb"), "--tileset", str(scratch / "tiles" / "tileset.json"), "--sfm",
                     str(project / "sfm"), "--images", str(images), "--quiet", "--json"]  # fmt: skip
        t_mesh, out, _, mb_mesh = child_with_tree(OURS, mesh_args)
        r = json.loads(out[out.index("{") :])
        print(f"survey: {project}")
        print(f"ortho (baseline): {t_ortho:.1f} s, peak {mb_ortho:.0f} MB (process tree)")
        print(f"mesh: {t_mesh:.1f} s, peak {mb_mesh:.0f} MB; ratio mesh/ortho {t_mesh / t_ortho:.2f} (target <= 1)")
        print(f"  {r['n_faces']:,} faces: {r['faces_per_ha']:,.0f} a hectare, {r['mb_per_ha']:.2f} MB a hectare (glTF)")
        print(
            f"  against the DSM: RMSE {r['rmse_m']:.3f} m (asked <= {r['max_rmse_m']:.3f}), "
            f"max {r['max_error_m']:.2f} m"
        )
        print(f"  3D Tiles: {r['n_tiles']} tiles in {r['n_levels']} levels")
        print(f"  walls: {r['wall_faces']:,} faces on their atlas, {r['wall_photo_share']:.0%} of their area by photo")
    return 0


if __name__ == "__main__":
    sys.exit(main())
