"""A textured mesh as glTF binary (``pygltflib``) and as OBJ+MTL.

glTF is y-up: a local east, north, up vertex is written as (east, up, -north), a proper rotation,
so faces counter-clockwise from above stay front faces. The photo texture is the colour itself:
the material is unlit (``KHR_materials_unlit``), so viewers do not shade it a second time.
OBJ has no axes of its own and GIS readers take it z-up: east, north, up, as the CRS has them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from geoortho.core.outputs import atomic_path

#: JPEG quality of the texture (a photo mosaic: PNG would be 3-4 times larger for no visible gain)
JPEG_QUALITY = 90


def encode_jpeg(rgb: np.ndarray) -> bytes:
    """An (h, w, 3) uint8 RGB image as JPEG bytes."""
    import cv2

    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    if not ok:
        raise RuntimeError("OpenCV could not encode the texture as JPEG")
    return buf.tobytes()


@dataclass(frozen=True)
class Part:
    """One textured piece of a mesh: ``enu`` (n, 3) local east, north, up; ``faces`` (m, 3),
    counter-clockwise from above; ``uv`` (n, 2), (0, 0) the texture's top-left; its JPEG."""

    name: str
    enu: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    jpeg: bytes


def glb_bytes(parts: list[Part], extras: dict[str, Any]) -> bytes:
    """Textured parts as one glTF binary: one node, one mesh, a primitive (and a material and
    texture of its own) for each part."""
    import pygltflib as g

    chunks: list[bytes] = []
    accessors: list[Any] = []
    primitives, materials, textures, images = [], [], [], []
    for i, part in enumerate(parts):
        enu = part.enu
        pos = np.ascontiguousarray(np.stack([enu[:, 0], enu[:, 2], -enu[:, 1]], axis=1), np.float32)
        tex = np.ascontiguousarray(part.uv, np.float32)
        idx = np.ascontiguousarray(part.faces, np.uint32).ravel()
        first = len(chunks)
        chunks += [pos.tobytes(), tex.tobytes(), idx.tobytes(), part.jpeg]
        accessors += [
            g.Accessor(bufferView=first, componentType=g.FLOAT, count=len(pos), type=g.VEC3,
                       min=pos.min(axis=0).tolist(), max=pos.max(axis=0).tolist()),
            g.Accessor(bufferView=first + 1, componentType=g.FLOAT, count=len(tex), type=g.VEC2),
            g.Accessor(bufferView=first + 2, componentType=g.UNSIGNED_INT, count=len(idx), type=g.SCALAR),
        ]  # fmt: skip
        primitives.append(
            g.Primitive(attributes=g.Attributes(POSITION=3 * i, TEXCOORD_0=3 * i + 1), indices=3 * i + 2, material=i)
        )
        materials.append(
            g.Material(
                name=part.name,
                pbrMetallicRoughness=g.PbrMetallicRoughness(
                    baseColorTexture=g.TextureInfo(index=i), metallicFactor=0.0, roughnessFactor=1.0
                ),
                doubleSided=True,  # a wall seen from behind (through a gap) still shows
                extensions={"KHR_materials_unlit": {}},
            )
        )
        textures.append(g.Texture(source=i, sampler=0))
        images.append(g.Image(bufferView=first + 3, mimeType="image/jpeg"))
    views, offset, blob = [], 0, b""
    for i, chunk in enumerate(chunks):
        kind = i % 4
        target = g.ARRAY_BUFFER if kind < 2 else (g.ELEMENT_ARRAY_BUFFER if kind == 2 else None)
        views.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=len(chunk), target=target))
        pad = (-len(chunk)) % 4  # every view starts 4-byte aligned (the spec's rule for accessors)
        blob += chunk + b"\0" * pad
        offset += len(chunk) + pad
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="geoortho", extras=extras),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[g.Node(mesh=0)],
        meshes=[g.Mesh(primitives=primitives)],
        materials=materials,
        extensionsUsed=["KHR_materials_unlit"],
        textures=textures,
        samplers=[
            g.Sampler(
                magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.CLAMP_TO_EDGE, wrapT=g.CLAMP_TO_EDGE
            )
        ],  # fmt: skip
        images=images,
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
    )
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())


def write_glb(path: Path, parts: list[Part], extras: dict[str, Any]) -> Path:
    """:func:`glb_bytes` written atomically to ``path``."""
    data = glb_bytes(parts, extras)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_obj(path: Path, parts: list[Part], header: str) -> Path:
    """The mesh as OBJ (east, north, up, in the local frame ``header`` states) with its MTL and a
    JPEG for each part beside it, named after it; each file written atomically.

    Written here, not by ``trimesh``: its OBJ holds one material per mesh, and it re-encodes
    textures as PNG (three to four times the JPEG's size)."""
    path = Path(path)
    mtl_name = path.with_suffix(".mtl").name
    lines = [f"# {ln}" for ln in header.splitlines()] + [f"mtllib {mtl_name}"]
    mtl = ["# geoortho: the photos' colours, unlit"]
    base = 0
    for i, part in enumerate(parts):
        texture_name = path.with_suffix(".jpg").name if i == 0 else f"{path.stem}_{part.name}.jpg"
        with atomic_path(path.with_name(texture_name)) as tmp:
            tmp.write_bytes(part.jpeg)
        mtl += [f"newmtl {part.name}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "illum 0", f"map_Kd {texture_name}"]
        lines += [f"o {part.name}"]
        lines += [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in part.enu.tolist()]
        lines += [f"vt {u:.6f} {t:.6f}" for u, t in _obj_uv(part.uv).tolist()]
        lines += [f"usemtl {part.name}"]
        f = part.faces + base + 1  # OBJ counts from 1, over the whole file
        lines += [f"f {a}/{a} {b}/{b} {c}/{c}" for a, b, c in f.tolist()]
        base += len(part.enu)
    with atomic_path(path.with_name(mtl_name)) as tmp:
        tmp.write_text("\n".join(mtl) + "\n", encoding="utf-8")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _obj_uv(uv: np.ndarray) -> np.ndarray:
    """OBJ's texture rows run up from the bottom (glTF's down from the top)."""
    return np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)
