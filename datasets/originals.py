"""Rebuild the data folder from the files' original public locations, without a mirror.

    python datasets/originals.py [--dest FOLDER] [--file meshes/bunny.ply ...] [--list]

Every source is pinned twice: a URL at a fixed commit of its public repository, and the
SHA-256 of the source file itself (pooch refuses a download that does not match). Each
source is then converted here, with the code below, and the result must equal the file of
``torch_brdf.data.REGISTRY`` byte for byte (a mismatch is refused and deleted, never kept):

* ``meshes/bunny.ply``, ``meshes/teapot.obj``: byte copies of the originals (no conversion);
* ``meshes/cornell/*.obj``: the Cornell box parts of Mitsuba's scene data, triangulated and
  re-oriented (:func:`cornell_part`);
* ``meshes/dragon_100k.ply``: the decimated Stanford dragon without its 4-vertex ground quad,
  positions and triangles only (:func:`strip_dragon`);
* ``envmaps/*.exr``: Poly Haven and Debevec probes, negatives clamped and downsampled with a
  solid-angle weighted block average, float32 ZIP EXR (:func:`convert_envmap`);
* ``merl/nbrdf_merl100_weights.npz``: the 100 NBRDF networks of the Neural-BRDF repository,
  repacked from Keras ``.h5`` files (:func:`pack_nbrdf`, needs ``h5py``);
* ``merl/merl_nbrdf_sample_f16.npz``: two of those networks evaluated on the downsampled MERL
  grid (:func:`nbrdf_table`).

One file cannot be rebuilt this way: ``meshes/cornell/materials.json`` holds RGB values we
derived from the published spectra (CIE 1931, Bradford to D65) with a tool that is not part of
this repository. The package does not read it (two scene tests do, and skip without it); get
it from a mirror (``torch-brdf fetch-data --url``) if you run those tests.

Byte equality of the converted files was checked with numpy 2, OpenEXR 3.3 and h5py 3 on
x86-64; another library version may encode the same numbers differently, in which case the
script says which file differs and keeps nothing of it.

Downloads are cached in ``$TORCH_BRDF_CACHE/originals``; finished outputs are kept, so an
interrupted run resumes. Prints one line per file, then one JSON object.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import os
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from torch_brdf.data import ENV_VAR, REGISTRY, cache_dir

RAW = "https://raw.githubusercontent.com"
MITSUBA_DATA = f"{RAW}/mitsuba-renderer/mitsuba-data/01100fa9b0b154492061a92404f26dcd7b784dbb"
PYTORCH3D = f"{RAW}/facebookresearch/pytorch3d/9381c4016376345bb795b97c45a6c2de66db354a"
THREE_HDRS = f"{RAW}/jianming2515/ITBE-2025-Fustion-Lab-Group6/26aab085e7b8b0925751b88c095da3afed6ff37e"
VOXEL_BUILDER = f"{RAW}/nimadez/voxel-builder/d62b3e8aa2534a023573121a6913dd7d80c84052"
PBRT_V2 = f"{RAW}/mmp/pbrt-v2/e6f6334f3c26ca29eba2b27af4e60fec9fdc7a8d"
DRAGON = f"{RAW}/djgrewal/python-mesh-deformation/84ec01bbf6b22e8f63f38e4326378427e0bcb7f0"
NEURAL_BRDF = f"{RAW}/asztr/Neural-BRDF/e229dda3308c78f05e57dbc9455326884f766301"

#: source key -> (URL at a fixed commit, SHA-256 of the file at that URL)
SOURCES: dict[str, tuple[str, str]] = {
    "bunny.ply": (
        f"{MITSUBA_DATA}/common/meshes/bunny.ply",
        "b9b363c443640e9e0ad202188457037241d6eb671fd575e188821fea4bd2042d",
    ),
    "teapot.obj": (
        f"{PYTORCH3D}/docs/tutorials/data/teapot.obj",
        "2f833c87e691d949dfa1325df94efe3c25e95b948c7f147e2d08e3ffb719fcda",
    ),
    "cbox/back.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/back.obj",
        "ed81a4609c6b1f26ba3e51dda2a99bf4570347e9532c32b69bea809959d09d43",
    ),
    "cbox/ceiling.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/ceiling.obj",
        "f94b8d956dd866bf992c8fdc7ba67cbf9e27c9da2867364520b544effa068468",
    ),
    "cbox/floor.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/floor.obj",
        "88fccaa05919ae3dd018152cb5b33e25951531f518d79801b1260d5a6c71fb2f",
    ),
    "cbox/greenwall.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/greenwall.obj",
        "c2f5e442828cfd613bb5f130fc599927dc0b15c990dbea5e0269e2ea1686110e",
    ),
    "cbox/largebox.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/largebox.obj",
        "23826d912d35685bbf1fa48e45826bc2e588f4e3fc6ea2c9900693da7249fd47",
    ),
    "cbox/luminaire.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/luminaire.obj",
        "7b731b62b30925436fd2fd5c6b14b71b50a8f8decb531c35c37c6d84815ea250",
    ),
    "cbox/redwall.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/redwall.obj",
        "7f4eb06f871477912fb10085c6f66fbac1f79b33183852036655f32d212d7fb0",
    ),
    "cbox/smallbox.obj": (
        f"{MITSUBA_DATA}/common/meshes/cbox/smallbox.obj",
        "15888f8cf12d0d791166d772fce279682d45322a3ca57bff49f63a667f7a0df2",
    ),
    "dragon.ply": (f"{DRAGON}/meshes/dragon.ply", "338fd2a1c8e11bf112b31d0137bb30dab236880ca353c3cc0819aaa2293e4d50"),
    "quarry_01_1k.hdr": (
        f"{THREE_HDRS}/textures/equirectangular/quarry_01_1k.hdr",
        "a3101f0ae89ed847dbed88da3ffa3ddb17b5acf8063099b26ceae08f640eea9b",
    ),
    "venice_sunset_1k.hdr": (
        f"{THREE_HDRS}/textures/equirectangular/venice_sunset_1k.hdr",
        "3a9e9674abfaca8782274efa60d8fdbc3036bccd232743cee963ee602a1ee264",
    ),
    "hdr_overcast_soil_puresky_1k.hdr": (
        f"{VOXEL_BUILDER}/src/assets/hdr_overcast_soil_puresky_1k.hdr",
        "2dbbbbb1323a8e8989db2e8306bd13099b215539e5adba41b85738a250a7904e",
    ),
    "grace_latlong.exr": (
        f"{PBRT_V2}/scenes/textures/grace_latlong.exr",
        "7c017bce200658354d72774712e51f039d472aa1399a91c2d0e3eb81ca909079",
    ),
    "merl_nbrdf.zip": (
        f"{NEURAL_BRDF}/data/merl_nbrdf.zip",
        "d1678c0cc5059f315d3d3284f36f3082787474106d72e3cae41fbad76d8f271a",
    ),
}

#: Cornell box output part -> (source part, how its triangles face)
CORNELL = {
    "floor": ("floor", "wall"),
    "ceiling": ("ceiling", "wall"),
    "back": ("back", "wall"),
    "left": ("redwall", "wall"),
    "right": ("greenwall", "wall"),
    "short_box": ("smallbox", "block"),
    "tall_box": ("largebox", "block"),
    "light": ("luminaire", "light"),
}
ROOM_CENTER = np.array([278.0, 274.4, 279.6])

#: the files this script cannot rebuild, and why
NOT_REBUILT = {
    "meshes/cornell/materials.json": "RGB values derived from the published spectra by a tool that is not "
    "in this repository (the package does not read it; two scene tests do, and skip without it)",
}


# ----------------------------------------------------------------------------- conversions


def _read_obj(data: bytes) -> tuple[np.ndarray, list[list[int]]]:
    verts, faces = [], []
    for line in data.decode().splitlines():
        tok = line.split()
        if tok and tok[0] == "v":
            verts.append([float(t) for t in tok[1:4]])
        elif tok and tok[0] == "f":
            faces.append([int(t.split("/")[0]) - 1 for t in tok[1:]])
    return np.array(verts, dtype=np.float64), faces


def cornell_part(name: str, source: bytes) -> bytes:
    """One Cornell box part as a triangulated OBJ in millimetres, y up: polygons become fans,
    unused vertices, normals and texture coordinates are dropped, and every triangle is wound
    counter-clockwise so that its normal points into the room (walls), out of the block
    (blocks) or down (the light). The ceiling keeps its outer rectangle only: the source's
    second, reversed polygon marks the light's opening, and the light sits just below it."""
    stem, role = CORNELL[name]
    v, faces = _read_obj(source)
    if name == "ceiling":
        faces = faces[:1]
    tris = np.array([[p[0], p[k], p[k + 1]] for p in faces for k in range(1, len(p) - 1)], dtype=np.int64)
    centroid = v[np.unique(tris)].mean(axis=0)
    for i, (a, b, c) in enumerate(tris.copy()):
        n = np.cross(v[b] - v[a], v[c] - v[a])
        p = (v[a] + v[b] + v[c]) / 3.0
        want = {"wall": ROOM_CENTER - p, "block": p - centroid, "light": np.array([0.0, -1.0, 0.0])}[role]
        if np.dot(n, want) < 0:
            tris[i] = [a, c, b]
    used = np.unique(tris)
    remap = -np.ones(len(v), dtype=np.int64)
    remap[used] = np.arange(len(used))
    lines = [
        f"# Cornell box part '{name}' (source part: {stem}.obj)",
        "# units: millimetres, y up; triangles wound counter-clockwise",
    ]
    lines += ["v {:.4f} {:.4f} {:.4f}".format(*p) for p in v[used]]
    lines += ["f {} {} {}".format(*t) for t in remap[tris] + 1]
    return ("\n".join(lines) + "\n").encode()


def strip_dragon(source: bytes) -> bytes:
    """The dragon PLY without the 4-vertex, 2-triangle ground quad its source carries (the last
    four vertices, at y = 0, +-25 in x and z), with positions and triangles only."""
    end = source.index(b"end_header\n") + len(b"end_header\n")
    header = source[:end].decode("ascii")
    nv = int(header.split("element vertex ")[1].split()[0])
    nf = int(header.split("element face ")[1].split()[0])
    vdt = np.dtype([(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")] + [("flags", "<i4")])
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,)), ("flags", "<i4")])
    v = np.frombuffer(source, vdt, nv, end)
    f = np.frombuffer(source, fdt, nf, end + nv * vdt.itemsize)
    assert (f["n"] == 3).all(), "the dragon's faces are triangles"
    keep_v = nv - 4
    ground = v[keep_v:]
    assert np.allclose(np.abs(ground["x"]), 25) and np.allclose(ground["y"], 0), "the ground quad is last"
    keep = (f["i"] < keep_v).all(axis=1)
    xyz = np.zeros(keep_v, np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4")]))
    for k in "xyz":
        xyz[k] = v[k][:keep_v]
    tris = np.zeros(int(keep.sum()), np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    tris["n"], tris["i"] = 3, f["i"][keep]
    out_header = (
        "ply\nformat binary_little_endian 1.0\n"
        "comment Stanford dragon, decimated to 100k triangles (ground quad removed)\n"
        f"element vertex {keep_v}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(tris)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    return out_header.encode("ascii") + xyz.tobytes() + tris.tobytes()


def read_rgbe(data: bytes) -> np.ndarray:
    """A Radiance RGBE (``.hdr``) image as (H, W, 3) float32 (flat or run-length scanlines)."""
    pos, fmt = 0, None
    while True:  # header lines up to the first empty one
        end = data.index(b"\n", pos)
        line = data[pos:end].decode("latin-1").strip()
        pos = end + 1
        if line.startswith("FORMAT="):
            fmt = line[len("FORMAT=") :]
        if line == "":
            break
    if fmt not in (None, "32-bit_rle_rgbe"):
        raise ValueError(f"unsupported Radiance format {fmt!r}")
    end = data.index(b"\n", pos)
    res = data[pos:end].decode("latin-1").split()
    pos = end + 1
    if len(res) != 4 or res[0] != "-Y" or res[2] != "+X":
        raise ValueError(f"unsupported resolution line {res!r}")
    h, w = int(res[1]), int(res[3])
    buf = np.frombuffer(data, dtype=np.uint8, offset=pos)
    rgbe = np.empty((h, w, 4), dtype=np.uint8)
    p = 0
    for y in range(h):
        if 8 <= w < 32768 and buf[p] == 2 and buf[p + 1] == 2 and (buf[p + 2] & 0x80) == 0:
            if (int(buf[p + 2]) << 8 | int(buf[p + 3])) != w:
                raise ValueError("scanline width mismatch")
            p += 4
            for c in range(4):
                row, x = rgbe[y, :, c], 0
                while x < w:
                    n = int(buf[p])
                    p += 1
                    if n > 128:  # a run
                        n -= 128
                        row[x : x + n] = buf[p]
                        p += 1
                    else:  # literal bytes
                        row[x : x + n] = buf[p : p + n]
                        p += n
                    x += n
        else:
            rgbe[y] = buf[p : p + 4 * w].reshape(w, 4)
            p += 4 * w
    e = rgbe[..., 3].astype(np.int32)
    scale = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0).astype(np.float32)
    return rgbe[..., :3].astype(np.float32) * scale[..., None]


def convert_envmap(source: bytes, is_exr: bool, width: int, flip_vertical: bool = False) -> bytes:
    """A lat-long map as a float32 RGB ZIP OpenEXR of ``width`` x ``width / 2``, row 0 the zenith:
    negatives clamped to 0, then an integer-factor block average with every source pixel weighted
    by its solid angle (sin theta), so the map's integral over the sphere is kept."""
    import OpenEXR

    with tempfile.TemporaryDirectory() as tmp:
        if is_exr:
            (Path(tmp) / "in.exr").write_bytes(source)
            with OpenEXR.File(str(Path(tmp) / "in.exr")) as f:
                ch = f.channels()
                img = ch["RGB"].pixels if "RGB" in ch else ch["RGBA"].pixels[..., :3]
            img = np.asarray(img, dtype=np.float32)
        else:
            img = read_rgbe(source)
        if flip_vertical:  # pbrt-v2's probe stores the nadir in row 0
            img = img[::-1]
        img = np.maximum(img, 0.0)
        h, w, _ = img.shape
        if w != width:
            k = w // width
            if w % width or h * 2 != w:
                raise ValueError(f"cannot downsample {w}x{h} to {width}x{width // 2}")
            theta = (np.arange(h) + 0.5) * np.pi / h
            wgt = np.sin(theta).astype(np.float64)[:, None, None]
            num = (img.astype(np.float64) * wgt).reshape(h // k, k, width, k, 3).sum(axis=(1, 3))
            den = np.broadcast_to(wgt, (h, w, 1)).reshape(h // k, k, width, k, 1).sum(axis=(1, 3))
            img = (num / den).astype(np.float32)
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        with OpenEXR.File(header, {"RGB": np.ascontiguousarray(img, dtype=np.float32)}) as f:
            f.write(str(Path(tmp) / "out.exr"))
        return (Path(tmp) / "out.exr").read_bytes()


def pack_nbrdf(zip_bytes: bytes) -> bytes:
    """The Neural-BRDF repository's 100 MERL networks (one Keras ``.h5`` per material) as one npz:
    ``names`` (sorted) and float32 ``W1 b1 W2 b2 W3 b3`` stacked over the materials."""
    import h5py

    names, arrays = [], {k: [] for k in ("W1", "b1", "W2", "b2", "W3", "b3")}
    with zipfile.ZipFile(io.BytesIO(zip_bytes)) as z:
        members = sorted(n for n in z.namelist() if n.endswith(".h5"))
        for member in members:
            with h5py.File(io.BytesIO(z.read(member)), "r") as f:
                for i in (1, 2, 3):
                    g = f[f"dense_{i}/dense_{i}"]
                    arrays[f"W{i}"].append(np.asarray(g["kernel:0"], dtype=np.float32))
                    arrays[f"b{i}"].append(np.asarray(g["bias:0"], dtype=np.float32))
            names.append(Path(member).stem)
    return _npz(names=np.array(names), **{k: np.stack(v) for k, v in arrays.items()})


def nbrdf_table(weights_npz: bytes, materials: list[str], td_step: int = 2, pd_step: int = 4) -> bytes:
    """NBRDF networks evaluated on the downsampled MERL grid (the layout of a MERL table:
    ``brdf`` float16 (N, 3, 90, T, P) with -1 where the incoming or outgoing direction is at or
    below the horizon for phi_h = 0, the kept indices, their angles, the RGB scale)."""
    w = np.load(io.BytesIO(weights_npz))
    all_names = [str(s) for s in w["names"]]
    th_idx, td_idx, pd_idx = np.arange(90), np.arange(0, 90, td_step), np.arange(0, 180, pd_step)
    th = (th_idx / 90.0) ** 2 * (np.pi / 2)
    td = td_idx * (np.pi / 2) / 90
    pd = pd_idx * np.pi / 180
    TH, TD, PD = np.meshgrid(th, td, pd, indexing="ij")
    d = np.stack([np.sin(TD) * np.cos(PD), np.sin(TD) * np.sin(PD), np.cos(TD)], -1)
    c, s = np.cos(TH)[..., None], np.sin(TH)[..., None]
    wi = np.concatenate([d[..., :1] * c + d[..., 2:] * s, d[..., 1:2], -d[..., :1] * s + d[..., 2:] * c], -1)
    h = np.concatenate([s, np.zeros_like(s), c], -1)
    wo = 2.0 * (wi * h).sum(-1, keepdims=True) * h - wi
    below = (wi[..., 2] <= 0) | (wo[..., 2] <= 0)
    f16_max = float(np.finfo(np.float16).max)
    x = np.stack([np.sin(TH), np.zeros_like(TH), np.cos(TH), d[..., 0], d[..., 1], d[..., 2]], -1)
    x = x.reshape(-1, 6).astype(np.float32)
    tables = []
    for name in sorted(materials):
        k = all_names.index(name)
        a = np.maximum(x @ w["W1"][k] + w["b1"][k], 0.0)
        a = np.maximum(a @ w["W2"][k] + w["b2"][k], 0.0)
        y = (np.exp(a @ w["W3"][k] + w["b3"][k]) - 1.0).reshape(TH.shape + (3,)).transpose(3, 0, 1, 2)
        y = np.maximum(y.astype(np.float64), 0.0)
        y[:, below] = -1.0
        tables.append(np.minimum(np.where(y < 0, -1.0, y), f16_max).astype(np.float16))
    return _npz(
        brdf=np.stack(tables),
        names=np.array(sorted(materials)),
        theta_h_index=th_idx.astype(np.int16),
        theta_d_index=td_idx.astype(np.int16),
        phi_d_index=pd_idx.astype(np.int16),
        theta_h=th.astype(np.float32),
        theta_d=td.astype(np.float32),
        phi_d=pd.astype(np.float32),
        scale=np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0]),
        source=np.array("nbrdf"),
    )


def _npz(**arrays) -> bytes:
    # np.savez_compressed through a file on disk, exactly as the published files were written
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "out.npz"
        np.savez_compressed(path, **arrays)
        return path.read_bytes()


# ----------------------------------------------------------------------------- recipes

_ENVMAPS = {
    "envmaps/quarry_01_sun_1024x512.exr": ("quarry_01_1k.hdr", 1024, False),
    "envmaps/quarry_01_sun_512x256.exr": ("quarry_01_1k.hdr", 512, False),
    "envmaps/venice_sunset_512x256.exr": ("venice_sunset_1k.hdr", 512, False),
    "envmaps/overcast_soil_puresky_512x256.exr": ("hdr_overcast_soil_puresky_1k.hdr", 512, False),
    "envmaps/grace_latlong_512x256.exr": ("grace_latlong.exr", 512, True),
}


def recipe(name: str):
    """``(source keys, build)`` for a data file: ``build(*sources) -> bytes``."""
    if name in ("meshes/bunny.ply", "meshes/teapot.obj"):
        return [Path(name).name], lambda data: data
    if name.startswith("meshes/cornell/") and name.endswith(".obj"):
        part = Path(name).stem
        return [f"cbox/{CORNELL[part][0]}.obj"], lambda data: cornell_part(part, data)
    if name == "meshes/dragon_100k.ply":
        return ["dragon.ply"], strip_dragon
    if name in _ENVMAPS:
        src, width, flip = _ENVMAPS[name]
        return [src], lambda data: convert_envmap(data, src.endswith(".exr"), width, flip)
    if name == "merl/nbrdf_merl100_weights.npz":
        return ["merl_nbrdf.zip"], pack_nbrdf
    if name == "merl/merl_nbrdf_sample_f16.npz":
        return ["merl_nbrdf.zip"], lambda z: nbrdf_table(pack_nbrdf(z), ["blue-acrylic", "gold-metallic-paint"])
    raise KeyError(name)


def download(key: str, progress: bool = False) -> bytes:
    """A source file's bytes, downloaded once into the cache and checked against its pin."""
    import pooch

    url, digest = SOURCES[key]
    path = pooch.retrieve(
        url,
        known_hash=f"sha256:{digest}",
        fname=key.replace("/", "_"),
        path=cache_dir() / "originals",
        progressbar=progress,
    )
    return Path(path).read_bytes()


def rebuild(dest: Path, names: list[str], progress: bool = False) -> dict:
    """Rebuild ``names`` into ``dest``; returns what was written, kept, refused or not rebuilt."""
    report = {"written": [], "kept": [], "mismatch": [], "not_rebuilt": {}}
    for name in names:
        target = dest / name
        if name in NOT_REBUILT:
            report["not_rebuilt"][name] = NOT_REBUILT[name]
            print(f"{name}: not rebuilt ({NOT_REBUILT[name]})")
            continue
        if target.is_file() and hashlib.sha256(target.read_bytes()).hexdigest() == REGISTRY[name]:
            report["kept"].append(name)
            print(f"{name}: present")
            continue
        keys, build = recipe(name)
        data = build(*(download(k, progress) for k in keys))
        got = hashlib.sha256(data).hexdigest()
        if got != REGISTRY[name]:
            report["mismatch"].append(name)
            print(f"{name}: rebuilt bytes differ from the pinned file (sha256 {got}); not kept", file=sys.stderr)
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.")
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, target)  # atomic: a reader never sees half a file
        report["written"].append(name)
        print(f"{name}: rebuilt from {', '.join(SOURCES[k][0] for k in keys)}")
    return report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dest", type=Path, default=None, help="data folder (default $TORCH_BRDF_DATA, else the cache's)")
    ap.add_argument("--file", action="append", default=None, help="a file of the registry (repeat; default all)")
    ap.add_argument("--list", action="store_true", help="print each file's sources and exit")
    args = ap.parse_args(argv)
    names = args.file or sorted(REGISTRY)
    unknown = sorted(set(names) - set(REGISTRY))
    if unknown:
        print(f"error: not in the data registry: {unknown}", file=sys.stderr)
        return 2
    if args.list:
        for name in names:
            srcs = NOT_REBUILT.get(name) or ", ".join(SOURCES[k][0] for k in recipe(name)[0])
            print(f"{name}: {srcs}")
        return 0
    dest = args.dest or Path(os.environ.get(ENV_VAR) or cache_dir() / "data").expanduser()
    report = rebuild(dest, names, progress=sys.stderr.isatty())
    print(json.dumps({"dest": str(dest), **report}))
    return 1 if report["mismatch"] else 0


if __name__ == "__main__":
    sys.exit(main())
