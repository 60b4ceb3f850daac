"""A textured mesh as glTF binary (``pygltflib``) and as OBJ+MTL (``trimesh``).

glTF is y-up: a local east, north, up vertex is written as (east, up, -north), a proper rotation,
so faces counter-clockwise from above stay front faces. The photo texture is the colour itself:
the material is unlit (``KHR_materials_unlit``), so viewers do not shade it a second time.
OBJ has no axes of its own and GIS readers take it z-up: east, north, up, as the CRS has them.
"""

from __future__ import annotations

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


def glb_bytes(enu: np.ndarray, faces: np.ndarray, uv: np.ndarray, jpeg: bytes, extras: dict[str, Any]) -> bytes:
    """One textured mesh as a glTF binary: ``enu`` (n, 3) local east, north, up; ``faces`` (m, 3),
    counter-clockwise from above; ``uv`` (n, 2), (0, 0) the texture's top-left corner."""
    import pygltflib as g

    pos = np.ascontiguousarray(np.stack([enu[:, 0], enu[:, 2], -enu[:, 1]], axis=1), np.float32)
    tex = np.ascontiguousarray(uv, np.float32)
    idx = np.ascontiguousarray(faces, np.uint32).ravel()
    chunks = [pos.tobytes(), tex.tobytes(), idx.tobytes(), jpeg]
    views, offset, blob = [], 0, b""
    for i, chunk in enumerate(chunks):
        target = g.ARRAY_BUFFER if i < 2 else (g.ELEMENT_ARRAY_BUFFER if i == 2 else None)
        views.append(g.BufferView(buffer=0, byteOffset=offset, byteLength=len(chunk), target=target))
        pad = (-len(chunk)) % 4  # every view starts 4-byte aligned (the spec's rule for accessors)
        blob += chunk + b"\0" * pad
        offset += len(chunk) + pad
    accessors = [
        g.Accessor(bufferView=0, componentType=g.FLOAT, count=len(pos), type=g.VEC3,
                   min=pos.min(axis=0).tolist(), max=pos.max(axis=0).tolist()),
        g.Accessor(bufferView=1, componentType=g.FLOAT, count=len(tex), type=g.VEC2),
        g.Accessor(bufferView=2, componentType=g.UNSIGNED_INT, count=len(idx), type=g.SCALAR),
    ]  # fmt: skip
    gltf = g.GLTF2(
        asset=g.Asset(version="2.0", generator="geoortho", extras=extras),
        scene=0,
        scenes=[g.Scene(nodes=[0])],
        nodes=[g.Node(mesh=0)],
        meshes=[
            g.Mesh(primitives=[g.Primitive(attributes=g.Attributes(POSITION=0, TEXCOORD_0=1), indices=2, material=0)])
        ],  # fmt: skip
        materials=[
            g.Material(
                pbrMetallicRoughness=g.PbrMetallicRoughness(
                    baseColorTexture=g.TextureInfo(index=0), metallicFactor=0.0, roughnessFactor=1.0
                ),
                doubleSided=True,  # a wall seen from behind (through a gap) still shows
                extensions={"KHR_materials_unlit": {}},
            )
        ],
        extensionsUsed=["KHR_materials_unlit"],
        textures=[g.Texture(source=0, sampler=0)],
        samplers=[
            g.Sampler(
                magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR, wrapS=g.CLAMP_TO_EDGE, wrapT=g.CLAMP_TO_EDGE
            )
        ],  # fmt: skip
        images=[g.Image(bufferView=3, mimeType="image/jpeg")],
        accessors=accessors,
        bufferViews=views,
        buffers=[g.Buffer(byteLength=len(blob))],
    )
    gltf.set_binary_blob(blob)
    return b"".join(gltf.save_to_bytes())


def write_glb(path: Path, enu: np.ndarray, faces: np.ndarray, uv: np.ndarray, jpeg: bytes,
              extras: dict[str, Any]) -> Path:  # fmt: skip
    """:func:`glb_bytes` written atomically to ``path``."""
    data = glb_bytes(enu, faces, uv, jpeg, extras)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_obj(path: Path, enu: np.ndarray, faces: np.ndarray, uv: np.ndarray, jpeg: bytes, header: str) -> Path:
    """The mesh as OBJ (east, north, up, in the local frame ``header`` states) with its MTL and
    its JPEG texture beside it, named after it; each file written atomically."""
    import trimesh
    from trimesh.exchange.obj import export_obj
    from trimesh.visual.material import SimpleMaterial
    from trimesh.visual.texture import TextureVisuals

    path = Path(path)
    texture_name = path.with_suffix(".jpg").name
    mtl_name = path.with_suffix(".mtl").name
    # the texture is named in the MTL; trimesh writes the image it holds, so it is given none and
    # the MTL is written here (the JPEG's own bytes, not a re-encoded PNG)
    mesh = trimesh.Trimesh(enu, faces, process=False,
                           visual=TextureVisuals(uv=_obj_uv(uv), material=SimpleMaterial(name="texture")))  # fmt: skip
    text = export_obj(mesh, include_normals=False, include_texture=True, write_texture=False, mtl_name=mtl_name,
                      digits=4, header=None)  # fmt: skip
    body = text if isinstance(text, str) else text[0]
    body = "\n".join(ln for ln in body.splitlines() if not ln.startswith("mtllib"))
    mtl = (
        "# geoortho: the orthophoto's colours, unlit\nnewmtl texture\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 0\n"
        f"map_Kd {texture_name}\n"
    )
    with atomic_path(path.with_name(texture_name)) as tmp:
        tmp.write_bytes(jpeg)
    with atomic_path(path.with_name(mtl_name)) as tmp:
        tmp.write_text(mtl, encoding="utf-8")
    with atomic_path(path) as tmp:
        tmp.write_text(
            "".join(f"# {ln}\n" for ln in header.splitlines()) + f"mtllib {mtl_name}\n" + body + "\n",
            encoding="utf-8",
        )
    return path


def _obj_uv(uv: np.ndarray) -> np.ndarray:
    """OBJ's texture rows run up from the bottom (glTF's down from the top)."""
    return np.stack([uv[:, 0], 1.0 - uv[:, 1]], axis=1)
