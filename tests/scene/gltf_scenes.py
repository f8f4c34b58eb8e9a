"""A small textured multi-material glTF scene written with trimesh (and pygltflib for what
trimesh does not write: a camera, KHR_materials_emissive_strength, KHR_lights_punctual)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def write_gltf_scene(path: Path, size: int = 24, light: str | None = "directional", seed: int = 0) -> Path:
    """Write a .glb (or .gltf) with a textured floor, a red box, an emissive panel, a camera node
    and (optionally) a KHR_lights_punctual light of type ``light``; return ``path``."""
    import pygltflib
    import trimesh
    from PIL import Image

    rng = np.random.default_rng(seed)
    tex = (rng.random((8, 8, 3)) * 255).astype(np.uint8)
    tex[0] = (255, 30, 30)
    pbr = trimesh.visual.material.PBRMaterial
    floor = trimesh.Trimesh([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2]], [[0, 2, 1], [0, 3, 2]], process=False)
    floor.visual = trimesh.visual.TextureVisuals(
        uv=np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float),
        material=pbr(name="wood", baseColorTexture=Image.fromarray(tex), metallicFactor=0.0, roughnessFactor=1.0),
    )
    box = trimesh.creation.box(extents=(1, 1, 1))
    box.apply_translation([0.3, 0.5, 0])
    box.visual = trimesh.visual.TextureVisuals(
        material=pbr(name="red", baseColorFactor=[200, 40, 30, 255], metallicFactor=0.0, roughnessFactor=1.0)
    )
    panel = trimesh.Trimesh([[-1, 2, -1], [1, 2, -1], [1, 2, 1], [-1, 2, 1]], [[0, 1, 2], [0, 2, 3]], process=False)
    panel.visual = trimesh.visual.TextureVisuals(
        material=pbr(name="glow", baseColorFactor=[0, 0, 0, 255], emissiveFactor=[1.0, 0.9, 0.8])
    )
    sc = trimesh.Scene()
    sc.add_geometry(floor, node_name="floor", geom_name="floor_mesh")
    sc.add_geometry(box, node_name="box", geom_name="box_mesh")
    sc.add_geometry(panel, node_name="panel", geom_name="panel_mesh")
    glb = Path(path).with_suffix(".glb")
    sc.export(glb)
    g = pygltflib.GLTF2().load(str(glb))
    for m in g.materials:
        if m.name == "glow":
            m.extensions = {"KHR_materials_emissive_strength": {"emissiveStrength": 3.0}}
    g.cameras = [
        pygltflib.Camera(type="perspective", perspective=pygltflib.Perspective(yfov=0.9, aspectRatio=1.0, znear=0.01))
    ]
    # a camera at (0, 2.5, 4) looking down at the origin: rotation about x by -atan(2.5/4)
    a = -np.arctan2(2.5, 4.0) / 2
    g.nodes.append(
        pygltflib.Node(
            name="eye", camera=0, translation=[0, 2.5, 4], rotation=[float(np.sin(a)), 0, 0, float(np.cos(a))]
        )
    )
    used = ["KHR_materials_emissive_strength"]
    if light is not None:
        g.extensions = {
            "KHR_lights_punctual": {"lights": [{"type": light, "name": "sun", "color": [1, 1, 1], "intensity": 2.0}]}
        }
        # shining along -z of a node tilted towards -y
        b = -np.pi / 6
        g.nodes.append(
            pygltflib.Node(
                name="sun",
                extensions={"KHR_lights_punctual": {"light": 0}},
                translation=[0, 3, 0],
                rotation=[float(np.sin(b)), 0, 0, float(np.cos(b))],
            )
        )
        used.append("KHR_lights_punctual")
    g.scenes[g.scene or 0].nodes.extend(range(len(g.nodes) - (2 if light else 1), len(g.nodes)))
    g.extensionsUsed = sorted(set((g.extensionsUsed or []) + used))
    out = Path(path)
    if out.suffix == ".gltf":
        g.convert_buffers(pygltflib.BufferFormat.DATAURI)
        g.save_json(str(out))
    else:
        g.save_binary(str(out))
    return out
