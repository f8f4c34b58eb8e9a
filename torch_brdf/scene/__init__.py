"""Scenes: meshes, embree ray tracing, camera, what the camera sees (G-buffer), lights and built-in scenes."""

from .builtin import (
    BUILTIN_SCENES,
    bunny_plane,
    bunny_relight,
    cornell_box,
    cornell_box_glossy,
    grid_plane,
    load_scene,
    mesh_scene,
    ring,
    teatray,
)
from .camera import Camera
from .envmap import EnvironmentMap, PointLightSet
from .gbuffer import GBuffer, trace_gbuffer
from .lights import AreaLight, DirectionalLight, Light, LightSample, LightSamples, PointLight, PointLights
from .mesh import DegenerateFacesWarning, load_mesh, mesh_from_arrays
from .raytrace import Hits, RayTracer
from .scene import Scene, SceneObject

__all__ = [
    "BUILTIN_SCENES",
    "AreaLight",
    "Camera",
    "DegenerateFacesWarning",
    "DirectionalLight",
    "EnvironmentMap",
    "GBuffer",
    "Hits",
    "Light",
    "LightSample",
    "LightSamples",
    "PointLight",
    "PointLightSet",
    "PointLights",
    "RayTracer",
    "Scene",
    "SceneObject",
    "bunny_plane",
    "bunny_relight",
    "cornell_box",
    "cornell_box_glossy",
    "grid_plane",
    "load_mesh",
    "load_scene",
    "mesh_from_arrays",
    "mesh_scene",
    "ring",
    "teatray",
    "trace_gbuffer",
]
