r"""Image textures on mesh UVs: reading, bilinear lookup, the texel under a ray hit.

A :class:`Texture` is a linear-RGB image. Colour textures stored in 8-bit formats (PNG,
JPEG) are decoded from sRGB (IEC 61966-2-1); EXR and Radiance ``.hdr`` are linear, and so are
non-colour maps (roughness, metallic) read with ``srgb=False``.

UV convention (OBJ's, trimesh's, Blender's): :math:`(u, v) = (0, 0)` is the *bottom-left*
corner of the image, :math:`v` grows upwards; a glTF file (top-left origin) is converted on
import. The lookup is bilinear between texel centres with repeating wrap, the lookup of
Mitsuba 3's ``bitmap`` texture (``filter_type = "bilinear"``, ``wrap_mode = "repeat"``), so
that a scene rendered by both sees the same texels.

A textured object carries per-vertex UVs (:attr:`SceneObject.uv`) and a texture per material
parameter it scales (:attr:`SceneObject.textures`, e.g. ``{"albedo": Texture}``): the
parameter's value at a surface point is the material's factor times the texel (glTF's
``baseColorFactor * baseColorTexture``, OBJ's ``Kd * map_Kd``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .._checks import MAX_IMAGE_PIXELS, MAX_IMAGE_SIDE
from ..errors import FileFormatError, SceneError

__all__ = [
    "Texture",
    "hit_uv",
    "read_texture",
    "srgb_to_linear",
    "surface_mean",
    "texture_at_hits",
    "texture_from_bytes",
    "texture_weight_map",
]

#: image files a texture can be read from
TEXTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr", ".hdr")


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """The sRGB decoding curve (IEC 61966-2-1) of values in [0, 1], float64."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


@dataclass(frozen=True, eq=False)
class Texture:
    """A linear-RGB image on a mesh's UVs.

    Attributes:
        image: (H, W, 3) float32 linear values, row 0 at the top of the image.
        name: a label (the file name, or the glTF image name).
        source: where it came from (a path), for messages.
    """

    image: torch.Tensor
    name: str = "texture"
    source: str = ""
    _mean: torch.Tensor = field(init=False, repr=False)

    def __post_init__(self):
        img = torch.as_tensor(self.image).detach().to(torch.float32).cpu()
        if img.ndim == 2:
            img = img[..., None].expand(-1, -1, 3)
        if img.ndim != 3 or img.shape[2] not in (1, 3, 4) or img.shape[0] < 1 or img.shape[1] < 1:
            raise SceneError(f"texture {self.name!r}: expected an (H, W, 3) image; got shape {tuple(img.shape)}")
        img = img[..., :3] if img.shape[2] >= 3 else img.expand(-1, -1, 3)
        if not bool(torch.isfinite(img).all()) or bool((img < 0).any()):
            raise SceneError(f"texture {self.name!r} ({self.source or 'array'}): values must be finite and >= 0")
        object.__setattr__(self, "image", img.contiguous())
        object.__setattr__(self, "_mean", img.double().mean((0, 1)).to(torch.float32))

    @property
    def mean(self) -> torch.Tensor:
        """(3,) mean texel: the albedo scale of later bounces in the GI approximation
        (Ben-Artzi et al. 2008, Sec. 5.3)."""
        return self._mean

    def lookup(self, uv: torch.Tensor) -> torch.Tensor:
        """Bilinear lookup with repeating wrap (Mitsuba's ``bitmap`` filter).

        Args:
            uv: (n, 2) texture coordinates, v up.
        Returns:
            (n, 3) float32 texel values.
        """
        h, w = self.image.shape[:2]
        uv = torch.as_tensor(uv).to(torch.float64)
        x = uv[:, 0] * w - 0.5
        y = (1.0 - uv[:, 1]) * h - 0.5
        x0, y0 = torch.floor(x), torch.floor(y)
        fx, fy = (x - x0)[:, None], (y - y0)[:, None]
        x0, y0 = x0.long(), y0.long()
        flat = self.image.reshape(-1, 3).double()

        def at(yy, xx):
            return flat[(yy % h) * w + (xx % w)]

        top = at(y0, x0) * (1 - fx) + at(y0, x0 + 1) * fx
        bottom = at(y0 + 1, x0) * (1 - fx) + at(y0 + 1, x0 + 1) * fx
        return (top * (1 - fy) + bottom * fy).to(torch.float32)

    def tinted(self, rgb) -> Texture:
        """The same texture multiplied by an RGB tint (3 values or one)."""
        t = torch.as_tensor(rgb, dtype=torch.float32).reshape(-1)
        return Texture(self.image * t, self.name, self.source)

    def digest_parts(self) -> list:
        """What a scene's content digest covers: the name and the texels."""
        return [self.name, self.image.numpy()]


def _read_8bit(path, srgb: bool) -> np.ndarray:
    """PNG/JPEG (a path or a binary file object) as (H, W, 3) float64, linear when ``srgb``."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            if w > MAX_IMAGE_SIDE or h > MAX_IMAGE_SIDE or w * h > MAX_IMAGE_PIXELS:
                raise FileFormatError(f"texture {path}: {w}x{h} pixels exceeds the caps ({MAX_IMAGE_SIDE} a side)")
            if im.mode in ("I;16", "I;16B", "I", "F"):
                a = np.asarray(im, dtype=np.float64)
                a = a / (65535.0 if im.mode.startswith("I;16") or a.max() > 255 else 255.0)
                a = np.repeat(a[..., None], 3, -1)
            else:
                a = np.asarray(im.convert("RGB"), dtype=np.float64) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError, Image.DecompressionBombError) as exc:
        raise FileFormatError(f"cannot read texture {getattr(path, 'name', path)}: {exc}") from None
    return srgb_to_linear(a) if srgb else a


def read_texture(path: str | os.PathLike, srgb: bool = True, name: str | None = None) -> Texture:
    """Read a texture file: PNG/JPEG (8 or 16 bit; decoded from sRGB when ``srgb``), EXR or ``.hdr`` (linear).

    Args:
        path: the image file.
        srgb: whether 8/16-bit values are sRGB-encoded colours (False: linear data such as roughness).
        name: label; the file name by default.
    Raises:
        FileFormatError: missing, unreadable, an unknown suffix, or beyond the size caps.
    """
    path = Path(path)
    if not path.is_file():
        raise FileFormatError(f"texture file not found: {path}")
    suffix = path.suffix.lower()
    if suffix in (".png", ".jpg", ".jpeg"):
        a = torch.from_numpy(_read_8bit(path, srgb).astype(np.float32))
    elif suffix == ".exr":
        from ..io.exr import read_exr

        a = read_exr(path, allow_gray=True)
    elif suffix == ".hdr":
        from ..io.hdr import read_hdr

        a = read_hdr(path)
    else:
        raise FileFormatError(f"texture {path}: unknown image type {suffix!r}; known: {list(TEXTURE_SUFFIXES)}")
    try:
        return Texture(a, name or path.name, str(path))
    except SceneError as exc:
        raise FileFormatError(str(exc)) from None


def texture_from_bytes(data: bytes, name: str, srgb: bool = True) -> Texture:
    """A PNG or JPEG texture from its bytes (an image embedded in a glTF file).

    Raises:
        FileFormatError: not a readable PNG/JPEG, or beyond the size caps.
    """
    import io

    buf = io.BytesIO(data)
    buf.name = name
    a = torch.from_numpy(_read_8bit(buf, srgb).astype(np.float32))
    try:
        return Texture(a, name, name)
    except SceneError as exc:
        raise FileFormatError(str(exc)) from None


def hit_uv(uv: np.ndarray | torch.Tensor, faces, prim_id: torch.Tensor, barycentrics: torch.Tensor) -> torch.Tensor:
    """UVs at ray hits on one object, interpolated like positions (embree's barycentrics).

    Args:
        uv: (V, 2) the object's per-vertex UVs.
        faces: (F, 3) the object's faces.
        prim_id: (n,) triangle index of each hit within the object.
        barycentrics: (n, 2) embree's (b1, b2).
    Returns:
        (n, 2) float64 UVs.
    """
    uv = torch.as_tensor(np.asarray(uv), dtype=torch.float64)
    f = torch.as_tensor(np.asarray(faces), dtype=torch.int64)[prim_id.long()]
    b = barycentrics.to(torch.float64)
    b0 = (1.0 - b[:, 0] - b[:, 1])[:, None]
    return b0 * uv[f[:, 0]] + b[:, :1] * uv[f[:, 1]] + b[:, 1:] * uv[f[:, 2]]


def texture_at_hits(scene, key: str, object_id: torch.Tensor, prim_id: torch.Tensor, barycentrics: torch.Tensor):
    """Texel multipliers of parameter ``key`` at hits on any objects of ``scene``.

    Args:
        scene: a :class:`~torch_brdf.scene.scene.Scene`.
        key: the material parameter (``"albedo"``, ``"kd"``, ``"base_color"`` ...).
        object_id: (n,) int64 object of each hit (-1: a miss).
        prim_id: (n,) int64 triangle of each hit within its object.
        barycentrics: (n, 2) embree's (b1, b2).
    Returns:
        (n, 3) float32: the texel where the object has a texture for ``key``, 1 elsewhere
        (and on misses); or None when no object has such a texture.
    """
    textured = [i for i, o in enumerate(scene.objects) if key in o.textures]
    if not textured:
        return None
    out = torch.ones(object_id.shape[0], 3)
    for i in textured:
        rows = torch.nonzero(object_id == i).squeeze(1)
        if rows.numel():
            o = scene.objects[i]
            out[rows] = o.textures[key].lookup(hit_uv(o.uv, o.mesh.faces, prim_id[rows], barycentrics[rows]))
    return out


def texture_weight_map(scene, obj: str, samples: int = 16, seed: int = 0, key: str = "base_color") -> torch.Tensor:
    r"""The texture as seen through the camera: the spatial weight map :math:`H^m(x)` of
    Ben-Artzi et al. 2008, Sec. 5.3, for object ``obj``.

    Each pixel averages the texel over ``samples`` jittered camera rays that hit the object
    (the paths a precomputation stores for that object's pixels start there); pixels the object
    does not cover get 1.

    Args:
        scene: the scene (its camera sets the size).
        obj: a textured object's name.
        samples: jittered rays per pixel.
        seed: of the jitter.
    Returns:
        (H, W, 3) float32.
    Raises:
        SceneError: unknown object, or it has no texture ``key``.
    """
    from .._checks import check_count

    samples = check_count(samples, "samples")
    m = scene.object_id(obj)
    o = scene.objects[m]
    if key not in o.textures:
        raise SceneError(f"object {obj!r} has no {key} texture")
    cam = scene.camera
    gen = torch.Generator().manual_seed(int(seed))
    total = torch.zeros(cam.height * cam.width, 3, dtype=torch.float64)
    count = torch.zeros(cam.height * cam.width, dtype=torch.float64)
    for _ in range(samples):
        origins, dirs = cam.generate_rays(jitter=True, generator=gen)
        hits = scene.trace(origins, dirs)
        rows = torch.nonzero(hits.object_id == m).squeeze(1)
        if rows.numel():
            uv = hit_uv(o.uv, o.mesh.faces, hits.prim_id[rows], hits.barycentrics[rows])
            total[rows] += o.textures[key].lookup(uv).double()
            count[rows] += 1
    out = torch.where(count[:, None] > 0, total / count.clamp_min(1)[:, None], 1.0)
    return out.to(torch.float32).reshape(cam.height, cam.width, 3)


def surface_mean(scene, obj: str, n: int = 4096, seed: int = 0, key: str = "base_color") -> torch.Tensor:
    """(3,) the texture's mean over the object's surface (area-weighted, ``n`` stratified-by-
    triangle random points): the albedo scale of bounces after the eye vertex (Sec. 5.3)."""
    o = scene.objects[scene.object_id(obj)]
    if key not in o.textures:
        raise SceneError(f"object {obj!r} has no {key} texture")
    v = np.asarray(o.mesh.vertices, dtype=np.float64)
    f = np.asarray(o.mesh.faces)
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    rng = np.random.default_rng(seed)
    tri = rng.choice(len(f), size=n, p=area / area.sum())
    r1, r2 = np.sqrt(rng.random(n)), rng.random(n)
    bary = torch.from_numpy(np.stack([(1 - r2) * r1, r2 * r1], -1))  # uniform on the triangle
    uv = hit_uv(o.uv, f, torch.from_numpy(tri), bary)
    return o.textures[key].lookup(uv).double().mean(0).to(torch.float32)
