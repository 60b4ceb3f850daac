"""Build the installable QGIS plugin zip: one top-level folder, geoortho_qgis/.

It holds geoortho/qgis_provider (the provider runs geoortho's CLI in geoortho's
own environment, so no other geoortho code goes in), and algorithms.json, the
registry description, so the algorithms are listed even before QGIS is told
where geoortho's Python is.

Usage: python tools/build_plugin.py [build/geoortho_qgis.zip]
"""

from __future__ import annotations

import json
import sys
import zipfile
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]
SOURCE = PROJECT / "geoortho" / "qgis_provider"
PLUGIN = "geoortho_qgis"  # not "geoortho": QGIS puts plugin folders on sys.path


def build(target: Path) -> Path:
    sys.path.insert(0, str(PROJECT))
    import geoortho
    from geoortho.processing.registry import describe

    description = describe()
    description.pop("package_dir")  # the build machine's, meaningless in the zip
    metadata = (SOURCE / "metadata.txt").read_text(encoding="utf-8")
    if f"version={geoortho.__version__}\n" not in metadata:
        raise SystemExit(f"{SOURCE / 'metadata.txt'}: version is not geoortho's {geoortho.__version__}")
    files = sorted(p for p in SOURCE.iterdir() if p.is_file() and p.suffix in (".py", ".txt", ".svg"))
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(f".{target.name}.tmp")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        for path in files:
            z.write(path, f"{PLUGIN}/{path.name}")
        z.writestr(f"{PLUGIN}/algorithms.json", json.dumps(description, indent=1) + "\n")
    tmp.replace(target)
    return target


if __name__ == "__main__":
    out = build(Path(sys.argv[1]) if len(sys.argv) > 1 else PROJECT / "build" / f"{PLUGIN}.zip")
    with zipfile.ZipFile(out) as z:
        print(f"{out}: {len(z.namelist())} files in {PLUGIN}/")
