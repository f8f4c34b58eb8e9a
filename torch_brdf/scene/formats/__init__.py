"""Scene files: TOML descriptions, glTF 2.0, Mitsuba 3 XML and OBJ+MTL, all read into one
:class:`~torch_brdf.scene.scene.Scene` by :func:`read_scene_file`."""

from __future__ import annotations

from pathlib import Path

from ...errors import SceneError
from ..scene import Scene
from ._common import ImportOptions, SceneFile, SubstitutionWarning

__all__ = ["SCENE_SUFFIXES", "ImportOptions", "SubstitutionWarning", "read_scene_file"]

#: scene file types by suffix
SCENE_SUFFIXES = {
    ".toml": "TOML scene description",
    ".gltf": "glTF 2.0",
    ".glb": "glTF 2.0 binary",
    ".xml": "Mitsuba 3 XML",
    ".obj": "Wavefront OBJ (+ MTL)",
}


def accepted_formats() -> str:
    """The accepted scene files, for messages."""
    return ", ".join(f"{k} ({v})" for k, v in SCENE_SUFFIXES.items())


def read_scene_file(path: str | Path, options: ImportOptions | None = None) -> Scene:
    """Read a scene file of any supported type (by suffix, see :data:`SCENE_SUFFIXES`).

    Args:
        path: the file.
        options: :class:`ImportOptions` (defaults: no references outside the file's folder, no
            substitutes, the file's image size).
    Raises:
        SceneError: an unknown suffix, or any problem in the file (naming file, element and problem).
    """
    options = options or ImportOptions()
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SCENE_SUFFIXES:
        raise SceneError(f"{path}: unknown scene file type {suffix or '(no suffix)'!r}; accepted: {accepted_formats()}")
    if not path.is_file():
        what = "is a directory" if path.is_dir() else "is not a file"
        raise SceneError(f"scene file not found: {path}" if not path.exists() else f"scene file {path} {what}")
    file = SceneFile(path, options)
    if suffix == ".toml":
        scene = Scene.from_toml(path)
        return scene.with_resolution(options.resolution) if options.resolution else scene
    if suffix in (".gltf", ".glb"):
        from .gltf import read_gltf

        return read_gltf(file)
    if suffix == ".xml":
        from .mitsuba_xml import read_mitsuba_xml

        return read_mitsuba_xml(file)
    from .obj import read_obj

    return read_obj(file)
