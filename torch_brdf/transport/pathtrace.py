r"""A plain wavefront path tracer with Lambert materials and next-event estimation.

This is the foundation's renderer (``torch-brdf render`` / ``demo``): unbiased for
Lambertian scenes, direct lighting when ``max_bounces == 1``. Materials of other types
are shaded with their ``diffuse`` albedo (a warning says so) until the BRDF layer lands.

Estimator. A path is traced from the eye; at every surface vertex each light is sampled
once (next-event estimation, with a shadow ray), then the path continues in a
cosine-distributed direction with throughput ``*= albedo`` (the exact ratio
:math:`f\cos\theta/p` for a Lambert BRDF). Emission is counted only where NEE cannot
see it: the environment and emitters seen directly from the eye. Surfaces are two-sided:
normals are flipped to face the arriving ray.

Reproducibility: every sample pass ``s`` uses its own generator seeded from
``(seed, s)``, so a render interrupted after ``k`` passes and resumed from its
checkpoint equals the uninterrupted render bit for bit.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from ..errors import ValueRangeError
from ..frame import to_world
from ..io.arrays import load_arrays, save_arrays
from ..scene.scene import Scene
from ..sphere.warps import square_to_cosine_hemisphere

CHECKPOINT_KIND = "pathtrace-checkpoint"


def diffuse_albedo_table(scene: Scene, dtype=torch.float32) -> torch.Tensor:
    """(num_objects, 3) Lambert albedo per object: ``albedo``, else ``diffuse``.

    Warns once per material that is not ``lambert`` (its non-diffuse part is ignored).
    """
    rows = []
    for obj in scene.objects:
        mat = scene.materials[obj.material]
        if mat["type"] != "lambert":
            warnings.warn(
                f"material {obj.material!r} of type {mat['type']!r}: rendered with its diffuse albedo only "
                "(the BRDF layer is not available to this renderer)",
                stacklevel=3,
            )
        rgb = mat.get("albedo", mat.get("diffuse", (0.5, 0.5, 0.5)))
        rows.append(torch.as_tensor(rgb, dtype=dtype).expand(3))
    return torch.stack(rows)


def _pass_generator(seed: int, pass_index: int) -> torch.Generator:
    g = torch.Generator()
    g.manual_seed(int(np.random.SeedSequence([seed, pass_index]).generate_state(1, np.uint64)[0] >> 1))
    return g


def _radiance(scene: Scene, origins, directions, albedo, max_bounces: int, gen) -> torch.Tensor:
    """One path per ray: (P, 3) radiance estimates (float32)."""
    p = origins.shape[0]
    out = torch.zeros(p, 3)
    env = scene.environment
    emitters = scene.area_lights
    hits = scene.trace(origins, directions)
    miss = ~hits.hit
    if env is not None and bool(miss.any()):
        out[miss] += env.eval_miss(directions[miss])
    for oid, light in emitters.items():
        on = hits.object_id == oid
        if bool(on.any()):
            out[on] += light.emitted(directions[on], hits.geometric_normal[on])
    # the active paths, compacted: pixel index, arriving direction, surface, throughput
    idx = torch.nonzero(hits.hit).squeeze(1)
    d_in, pos = directions[idx], hits.position[idx]
    ng, ns, oid = hits.geometric_normal[idx], hits.normal[idx], hits.object_id[idx]
    beta = torch.ones(idx.numel(), 3)
    for bounce in range(max_bounces):
        if idx.numel() == 0:
            break
        flip = torch.where((d_in * ng).sum(-1, keepdim=True) > 0, -1.0, 1.0)
        ng, ns = ng * flip, ns * flip
        ns = torch.where((ns * ng).sum(-1, keepdim=True) > 0, ns, ng)
        beta = beta * albedo[oid]
        for light in scene.lights:
            ls = light.sample(pos, gen)
            cos = (ls.direction * ns).sum(-1)
            k = torch.nonzero((cos > 0) & ((ls.direction * ng).sum(-1) > 0) & (ls.pdf > 0)).squeeze(1)
            if k.numel() == 0:
                continue
            k = k[scene.visible(pos[k], ng[k], ls.direction[k], ls.distance[k])]
            out.index_add_(0, idx[k], beta[k] * ls.weight[k] * (cos[k, None] / torch.pi))
        if bounce == max_bounces - 1:
            break
        # continue the path: cosine sampling makes f cos / pdf = albedo (applied above)
        wi = to_world(square_to_cosine_hemisphere(torch.rand(idx.numel(), 2, generator=gen)), ns)
        ok = torch.nonzero((wi * ng).sum(-1) > 0).squeeze(1)
        sub = scene.trace(scene.spawn(pos[ok], ng[ok], wi[ok]), wi[ok])
        keep = ok[sub.hit]
        idx, beta, d_in = idx[keep], beta[keep], wi[keep]
        pos, ng, ns, oid = (x[sub.hit] for x in (sub.position, sub.geometric_normal, sub.normal, sub.object_id))
    return out


def path_trace(
    scene: Scene,
    spp: int = 16,
    max_bounces: int = 4,
    seed: int = 0,
    chunk: int = 1 << 16,
    checkpoint: str | Path | None = None,
    checkpoint_every: int = 4,
    progress: bool = True,
) -> torch.Tensor:
    """Render ``scene`` from its camera: (H, W, 3) float32 linear radiance.

    Args:
        scene: the scene (Lambert materials; see the module docstring).
        spp: samples (paths) per pixel, each through a jittered point of the pixel.
        max_bounces: surface vertices per path; 1 is direct lighting only.
        seed: the render is a deterministic function of (scene, spp, max_bounces, seed).
        chunk: rays traced together (memory vs. overhead).
        checkpoint: file to save progress to every ``checkpoint_every`` passes and to
            resume from when it exists with matching settings (npz, versioned, checksummed).
        progress: show a tqdm bar over sample passes.
    """
    if spp < 1 or max_bounces < 1:
        raise ValueRangeError(f"spp and max_bounces must be >= 1; got spp={spp}, max_bounces={max_bounces}")
    cam = scene.camera
    h, w = cam.height, cam.width
    albedo = diffuse_albedo_table(scene)
    settings = {"scene": scene.name, "width": w, "height": h, "spp": spp, "max_bounces": max_bounces, "seed": seed}
    total = torch.zeros(h * w, 3, dtype=torch.float64)
    start = 0
    if checkpoint is not None and Path(checkpoint).exists():
        arrays, meta = load_arrays(checkpoint, kind=CHECKPOINT_KIND)
        if meta.get("settings") == settings:
            total = torch.from_numpy(arrays["sum"])
            start = int(meta["passes_done"])
    bar = tqdm(range(start, spp), total=spp, initial=start, desc=f"path trace {scene.name}", disable=not progress)
    for s in bar:
        gen = _pass_generator(seed, s)
        o, d = cam.generate_rays(jitter=True, generator=gen)
        for a in range(0, h * w, chunk):
            sl = slice(a, min(a + chunk, h * w))
            total[sl] += _radiance(scene, o[sl], d[sl], albedo, max_bounces, gen).double()
        done = s + 1
        if checkpoint is not None and (done % checkpoint_every == 0 or done == spp):
            save_arrays(
                checkpoint,
                {"sum": total.numpy()},
                kind=CHECKPOINT_KIND,
                meta={"settings": settings, "passes_done": done},
            )
    return (total / spp).to(torch.float32).reshape(h, w, 3)
