"""Input folders an output must not change: what a photo folder's reading takes for a photo, and
the guard the faces and the chain put on every output path.

Light on purpose (pathlib only): the registry uses it to check values before any stage is imported.
"""

from __future__ import annotations

from pathlib import Path

from geoortho.errors import InputError, ParameterError

__all__ = ["IMAGE_EXTENSIONS", "PROJECT_DSM", "path_inside", "project_dsm", "refuse_writing_into"]


#: What the reading of a photo folder takes for a photo.
IMAGE_EXTENSIONS = (".jpg", ".jpeg", ".tif", ".tiff")

#: A run project's DSM, inside its folder: what a project given for a surface stands for (change).
PROJECT_DSM = "dem/dsm.tif"

#: Output files that may replace their own earlier copy inside an input folder: the report of a
#: project is written into the project it reads.
_REWRITES_IN = {("output", "project"): (".html",)}


def project_dsm(path: Path) -> Path:
    """A surface given as a file, or as a run project's folder: its :data:`PROJECT_DSM`."""
    if not path.is_dir():
        return path
    if not (path / PROJECT_DSM).is_file():
        raise InputError(f"a folder without {PROJECT_DSM}: give a DSM or a run project", path=path)
    return path / PROJECT_DSM


def path_inside(path: Path, folder: Path) -> Path | None:
    """``path`` relative to ``folder`` when it lies in it (through symlinks), else None."""
    for a, b in ((path.resolve(), folder.resolve()), (path.absolute(), folder.absolute())):
        try:
            return a.relative_to(b)
        except ValueError:
            continue
    return None


def refuse_writing_into(out_name: str, out_path: Path, in_name: str, in_folder: Path) -> None:
    """Refuse an output file whose writing would change what an input folder holds: a file of it
    replaced (photos are read from the folder itself, not below it), or a new image that the next
    reading of a photo folder would take for a photo."""
    rel = path_inside(out_path, in_folder)
    if rel is None:
        return
    photos = in_name == "images"
    if photos and len(rel.parts) > 1:
        return  # below the photos' folder: a project folder kept beside the photos
    why = ""
    if out_path.exists():
        if out_path.suffix.lower() not in _REWRITES_IN.get((out_name, in_name), ()):
            why = "is a file of the input folder: writing it would destroy it"
    elif photos and out_path.suffix.lower() in IMAGE_EXTENSIONS:
        why = "would be read as a photo of the input folder"
    if why:
        raise ParameterError(out_name, f"{out_path} {why} (the input {in_name}): give a path outside that folder")
