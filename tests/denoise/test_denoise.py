"""Denoising basis images keeps every edit exact: linearity of the guide-only filters
(à-trous and local regression),
OIDN per basis image (edits exact given the denoised bases), freeze/denoise commutation,
guide buffers and their file round trip, HDR-FLIP."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from torch_brdf.denoise import (
    AtrousSettings,
    CumulativeOIDN,
    EdgeAwareFilter,
    GuideBuffers,
    GuideWeights,
    OIDNBasis,
    RegressionFilter,
    RegressionSettings,
    SelectedRegressionFilter,
    SelectionSettings,
    denoise,
    denoise_tensors,
    guide_buffers,
    make_denoiser,
    mean_tensors,
    oidn_available,
    oidn_frame,
    silhouette_signature,
)
from torch_brdf.errors import FileFormatError, ShapeError, ValueRangeError
from torch_brdf.io.arrays import load_arrays, save_arrays
from torch_brdf.records import PolynomialTensors
from torch_brdf.records.guides import GUIDE_NAMES, GUIDE_VERSION
from torch_brdf.render.polynomial import PolynomialRenderer
from torch_brdf.scene.builtin import cornell_box
from torch_brdf.transport.guides import light_lobe_images
from torch_brdf.transport.polynomial import PolynomialSettings, precompute_polynomial

needs_oidn = pytest.mark.skipif(not oidn_available(), reason="pyoidn not installed (optional extra 'denoise')")
SIZE = 24


@pytest.fixture(scope="module")
def setup():
    sc = cornell_box(SIZE)
    sc.materials["glossy"] = {"type": "blinn_phong", "kd": 0.2, "ks": 0.6, "exponent": 100.0}
    sc.objects[sc.object_id("back")].material = "glossy"
    tensors = precompute_polynomial(sc, PolynomialSettings("8,1,1", spp=4), seed=2, progress=False)
    mats = {o.name: sc.materials[o.material] for o in sc.objects if o.editable}
    guides = guide_buffers(sc)
    return sc, tensors, mats, guides


def _random_edit(R, tensors, gen):
    """Random coefficients (c, d) for every editable object: (H, W, 3) frame of R."""
    for m, b in enumerate(tensors.bases):
        if b is None:
            continue
        c = torch.rand(b.size, 3, generator=gen, dtype=torch.float64)
        d = torch.rand(3, generator=gen, dtype=torch.float64)
        R.set_coefficients(tensors.object_names[m], c, d=d)


def _rel(a, b):
    return float((a - b).abs().max() / b.abs().max())


def test_guides_trace_pixel_centres(setup):
    sc, _, _, g = setup
    o, d = sc.camera.generate_rays()
    hits = sc.trace(o, d)
    assert torch.equal(g.object_id.reshape(-1), hits.object_id)
    n = g.normal.reshape(-1, 3)[hits.hit]
    assert bool(((n * d[hits.hit]).sum(-1) <= 1e-6).all())  # facing the eye
    torch.testing.assert_close(n.norm(dim=-1), torch.ones(n.shape[0]))
    # the albedo proxy is a function of the object id only
    for m in g.object_id.unique().tolist():
        a = g.albedo[g.object_id == m]
        assert bool((a == a[0]).all())
    assert bool((g.albedo[g.object_id < 0] == 0).all())
    # mirror guides: what the mirror ray sees, geometry and lights only
    sees_light = g.mirror_radiance.sum(-1) > 0
    assert int(sees_light.sum()) > 0
    assert bool((g.mirror_id[sees_light] == sc.object_id("light")).all())
    assert bool((g.mirror_id[g.object_id < 0] == -2).all())
    assert float(g.light_cos_h.abs().max()) <= 1 + 1e-6
    assert bool((g.light_cos_h[g.object_id < 0] == 0).all())
    # the back wall faces the light's reflection: its half-vector cosine comes near 1
    assert float(g.light_cos_h[g.object_id == sc.object_id("back")].max()) > 0.99


def test_guides_file_round_trip_and_version(setup, tmp_path):
    g = setup[3]
    p = save_arrays(tmp_path / "g.npz", g.to_arrays(), kind="test")
    back = GuideBuffers.from_arrays(load_arrays(p, kind="test")[0])
    for k in GUIDE_NAMES:
        assert torch.equal(getattr(back, k), getattr(g, k))
    assert back.pixel_angle == g.pixel_angle
    assert GuideBuffers.from_arrays({}) is None
    arrays = g.to_arrays()
    arrays["guide_meta"] = arrays["guide_meta"].copy()
    arrays["guide_meta"][1] = 99
    with pytest.raises(FileFormatError):
        GuideBuffers.from_arrays(arrays)


def test_guides_are_saved_with_the_tensors(setup, tmp_path):
    _, tensors, _, g = setup
    # precompute_polynomial attaches the view's guides by default, versioned in the record
    assert tensors.meta["guides"] == GUIDE_VERSION
    for k in GUIDE_NAMES:
        assert torch.equal(getattr(tensors.guides, k), getattr(g, k))
    back = PolynomialTensors.load(tensors.save(tmp_path / "t.npz"))
    for k in GUIDE_NAMES:
        assert torch.equal(getattr(back.guides, k), getattr(g, k))
    plain = dataclasses.replace(tensors, guides=None)
    assert PolynomialTensors.load(plain.save(tmp_path / "plain.npz")).guides is None
    # the filter of a record is built from its own guides and bases
    A = EdgeAwareFilter.for_tensors(back)
    assert A.glossy == tuple(_glossy(tensors))
    x = torch.rand(3, SIZE, SIZE, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(A(x), EdgeAwareFilter(g, glossy=_glossy(tensors))(x))
    with pytest.raises(ValueRangeError):
        EdgeAwareFilter.for_tensors(plain)


def test_filter_is_linear_and_respects_object_ids(setup, gen):
    g = setup[3]
    A = EdgeAwareFilter(g, glossy=_glossy(setup[1]))
    x, y = torch.rand(2, 3, SIZE, SIZE, generator=gen, dtype=torch.float64)
    a, b = 0.7, -1.3
    torch.testing.assert_close(A(a * x + b * y), a * A(x) + b * A(y), rtol=1e-12, atol=1e-12)
    # a constant image stays constant (weights sum to 1), and an indicator of one object's
    # interior pixels never leaks out of them
    torch.testing.assert_close(
        A(torch.ones(SIZE, SIZE, dtype=torch.float64)), torch.ones(SIZE, SIZE, dtype=torch.float64)
    )
    back = setup[0].object_id("back")
    inside = A.interior & (g.object_id == back)
    out = A(inside.double())
    assert float(out[~inside].abs().max()) == 0.0
    # silhouette pixels are left as they are
    sil = ~A.interior
    torch.testing.assert_close(A(x)[:, sil], x[:, sil])
    # and the filter does smooth: noise inside a diffuse object drops (on the glossy back wall
    # the half-vector guide keeps it from smoothing much at this resolution)
    diffuse = [o for o in g.object_id.unique().tolist() if o >= 0 and o not in _glossy(setup[1])]
    biggest = max(diffuse, key=lambda o: int((A.interior & (g.object_id == o)).sum()))
    floor = A.interior & (g.object_id == biggest)
    assert int(floor.sum()) >= 30
    noise = torch.rand(SIZE, SIZE, generator=gen, dtype=torch.float64) * floor
    assert float(A(noise)[floor].std()) < 0.5 * float(noise[floor].std())
    with pytest.raises(ShapeError):
        A(torch.zeros(3, 5, 5))
    with pytest.raises(ValueRangeError):
        AtrousSettings(levels=0)


def _glossy(tensors):
    return [m for m, b in enumerate(tensors.bases) if b is not None and b.J > 1]


@pytest.fixture(scope="module")
def halves(setup):
    """Two independent 2-spp records of the setup's scene and their frames (C, H, W)."""
    sc, _, mats, _ = setup
    recs = [precompute_polynomial(sc, PolynomialSettings("8,1,1", spp=2), seed=s, progress=False) for s in (3, 4)]
    frames = [PolynomialRenderer(r, mats, dtype=torch.float64).evaluate().permute(2, 0, 1) for r in recs]
    return recs, frames


LINEAR_FILTERS = ["atrous", "regression", "selected"]


def _linear_filter(name, setup, halves):
    g, gl = setup[3], _glossy(setup[1])
    if name == "selected":  # the pick comes from fixed data (two half buffers), then is frozen
        return SelectedRegressionFilter(g, [tuple(halves[1])], glossy=gl)
    return {"atrous": EdgeAwareFilter, "regression": RegressionFilter}[name](g, glossy=gl)


@pytest.mark.parametrize("cls", LINEAR_FILTERS)
def test_denoised_tensors_evaluate_to_the_filtered_frame(setup, halves, gen, cls):
    """(a) linearity: the denoised record at random (c, d) equals the filter applied to the
    noisy record's frame at the same (c, d) (minus the emission, which is not filtered)."""
    _, tensors, mats, _ = setup
    A = _linear_filter(cls, setup, halves)
    den = denoise_tensors(tensors, A)
    assert den.meta["denoised"] == A.description
    R = PolynomialRenderer(tensors, mats, dtype=torch.float64)
    D = PolynomialRenderer(den, mats, dtype=torch.float64)
    e = tensors.emission.double().T.reshape(SIZE, SIZE, 3)
    for _ in range(3):
        state = gen.get_state()
        _random_edit(R, tensors, gen)
        gen.set_state(state)
        _random_edit(D, tensors, gen)
        noisy, clean = R.evaluate(), D.evaluate()
        expected = A((noisy - e).permute(2, 0, 1)).permute(1, 2, 0) + e
        assert _rel(clean, expected) < 1e-5  # float32 tensors, float64 evaluation
    with pytest.raises(ValueRangeError):
        denoise_tensors(tensors, A, max_entries=10)


def _frozen_frames(tensors, mats, obj, gen, n=3, den=None):
    R = PolynomialRenderer(tensors, mats, dtype=torch.float64)
    R.freeze(obj, denoiser=den)
    b = tensors.bases[tensors.object_id(obj)]
    frames = []
    for _ in range(n):
        R.set_coefficients(
            obj,
            torch.rand(b.size, 3, generator=gen, dtype=torch.float64),
            d=torch.rand(3, generator=gen, dtype=torch.float64),
        )
        frames.append(R())
    return frames, R


@pytest.mark.parametrize("cls", LINEAR_FILTERS)
@pytest.mark.parametrize("obj", ["back", "left"])
def test_freeze_after_denoise_equals_denoise_after_freeze(setup, halves, obj, cls):
    _, tensors, mats, _ = setup
    A = _linear_filter(cls, setup, halves)
    after, _ = _frozen_frames(denoise_tensors(tensors, A), mats, obj, torch.Generator().manual_seed(5))
    before, R = _frozen_frames(tensors, mats, obj, torch.Generator().manual_seed(5), den=A)
    for a, b in zip(after, before, strict=True):
        assert _rel(a, b) < 1e-5
    # the denoised frozen tensor covers about the same pixels as the noisy one (same frame
    # cost): it gains only pixels where no path of these 4 spp left a record; the selection's
    # silhouette candidates also spread a record along its edge (to pixels whose 3 x 3
    # neighbourhood sees the object too), more of them at this toy spp
    _, noisy = _frozen_frames(tensors, mats, obj, torch.Generator(), n=0)
    for k in ("pix_i", "pix_r"):
        assert R._frozen[k].numel() <= (1.15 if cls == "selected" else 1.05) * noisy._frozen[k].numel()
    oid = setup[3].object_id
    near = torch.nn.functional.max_pool2d((oid == tensors.object_id(obj)).double()[None, None], 3, 1, 1)[0, 0]
    gained = ~torch.isin(R._frozen["pix_i"], noisy._frozen["pix_i"])
    assert bool((near.flatten()[R._frozen["pix_i"][gained]] > 0).all())


def test_denoise_uses_the_guides_the_precomputation_attached(setup, gen):
    """``denoise(tensors)`` needs no guides from the user, and ``freeze(obj, denoiser="linear")``
    (the public way to denoise a frozen tensor) renders what freezing the denoised tensors does."""
    _, tensors, mats, g = setup
    den = denoise(tensors)
    ref = denoise_tensors(tensors, EdgeAwareFilter(g, glossy=_glossy(tensors)))
    R = PolynomialRenderer(den, mats, dtype=torch.float64)
    Q = PolynomialRenderer(ref, mats, dtype=torch.float64)
    state = gen.get_state()
    _random_edit(R, tensors, gen)
    gen.set_state(state)
    _random_edit(Q, tensors, gen)
    torch.testing.assert_close(R.evaluate(), Q.evaluate(), rtol=0, atol=0)
    # freeze after denoise == denoise after freeze, through the public API only
    after, _ = _frozen_frames(den, mats, "back", torch.Generator().manual_seed(9))
    before, F = _frozen_frames(tensors, mats, "back", torch.Generator().manual_seed(9), den="linear")
    assert F.frozen_object == "back" and F.frozen_denoiser.startswith("linear")
    for a, b in zip(after, before, strict=True):
        assert _rel(a, b) < 1e-5
    # and it is not the noisy frame (the filter did something)
    noisy, _ = _frozen_frames(tensors, mats, "back", torch.Generator().manual_seed(9))
    assert _rel(before[0], noisy[0]) > 1e-3
    # without guides: a clear error, not a silent noisy frame
    plain = dataclasses.replace(tensors, guides=None)
    with pytest.raises(ValueRangeError):
        denoise(plain)
    with pytest.raises(ValueRangeError):
        PolynomialRenderer(plain, mats).freeze("back", denoiser="linear")
    with pytest.raises(ValueRangeError):
        denoise(tensors, "bilateral")
    # the regression filter by name: the record's own guides and banded objects
    _, Q = _frozen_frames(tensors, mats, "back", torch.Generator(), n=0, den="regression")
    assert Q.frozen_denoiser == RegressionFilter.for_tensors(tensors).description


def test_cumulative_oidn_by_name(setup):
    """``freeze(obj, denoiser="cumulative")``'s denoiser: (d) over the regression filter of the
    record's guides and banded objects (no OIDN is run to build it)."""
    _, tensors, _, g = setup
    den = make_denoiser(g, "cumulative", _glossy(tensors), RegressionSettings(radius=3))
    assert isinstance(den, CumulativeOIDN) and den.mix == 0.0
    assert isinstance(den.fallback, RegressionFilter)
    assert (
        den.fallback.description
        == RegressionFilter(g, RegressionSettings(radius=3), glossy=_glossy(tensors)).description
    )
    with pytest.raises(ValueRangeError, match="'cumulative'"):
        make_denoiser(g, "cumulative_oidn")


def test_precompute_without_guides(setup):
    sc = setup[0]
    t = precompute_polynomial(sc, PolynomialSettings("2,1", spp=1, guides=False), seed=0, progress=False)
    assert t.guides is None and t.meta["guides"] is None


@needs_oidn
@pytest.mark.parametrize("kind", ["basis", "cumulative", "cumulative_lobes"])
def test_oidn_basis_edits_are_exact_given_the_denoised_bases(setup, gen, kind):
    """(b) OIDN is not linear, but it runs once on fixed basis images: afterwards the frozen
    tensor is fixed data (no OIDN per edit) and every frame is linear in the edited
    coefficients: frame(c1 + c2) = frame(c1) + frame(c2) - frame(0) at fixed d. Likewise (d),
    with and without the back wall's light lobes."""
    sc, tensors, mats, g = setup
    if kind == "basis":
        ob = OIDNBasis(g)
    elif kind == "cumulative":
        ob = CumulativeOIDN(g)
    else:
        lobes = light_lobe_images(sc, tensors.bases[tensors.object_id("back")], "back")
        ob = CumulativeOIDN(g, lobes=lobes)
    _, R = _frozen_frames(tensors, mats, "back", gen, n=0, den=ob)
    calls, fz = ob.calls, R._frozen
    assert calls > 0
    b = tensors.bases[tensors.object_id("back")]
    d = torch.rand(3, generator=gen, dtype=torch.float64)
    c1, c2 = torch.rand(2, b.size, 3, generator=gen, dtype=torch.float64)
    frames = []
    for c in (c1, c2, c1 + c2, torch.zeros_like(c1)):
        R.set_coefficients("back", c, d=d)
        frames.append(R())
    assert R._frozen is fz and ob.calls == calls  # edits never call the denoiser
    assert R.frozen_denoiser == ob.description
    f1, f2, f12, f0 = frames
    torch.testing.assert_close(f12, f1 + f2 - f0, rtol=0, atol=1e-6 * float(f12.abs().max()))
    assert bool(torch.isfinite(f12).all()) and float(f12.min()) >= 0


@needs_oidn
def test_oidn_group_sums_equal_oidn_of_the_group(setup, gen):
    g = setup[3]
    ob = OIDNBasis(g, min_occupancy=2.0)  # never satisfied: one group per term
    imgs = torch.rand(4, 3, SIZE, SIZE, generator=gen) * (torch.rand(4, 1, SIZE, SIZE, generator=gen) < 0.3)
    out = ob(imgs, torch.zeros(4, dtype=torch.long))
    from torch_brdf.denoise import oidn_image

    whole = oidn_image(imgs.sum(0).permute(1, 2, 0), g).permute(2, 0, 1)
    inner = ob.linear.interior
    lin_sum = ob.linear(imgs).sum(0)
    keep = inner & (lin_sum > 0).all(0)
    torch.testing.assert_close(out.sum(0)[:, keep], whole[:, keep], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out[:, :, ~inner], imgs[:, :, ~inner])


def test_cumulative_oidn_denoises_the_prefix_sums_of_each_group(setup, gen):
    """CumulativeOIDN: the bands of a group, summed up to band k, are the image denoiser's output
    on the noisy prefix sum S_k at the interior pixels holding a record of the group (so with an
    identity denoiser the bands come back unchanged); everything else is the fallback filter."""
    g = setup[3]
    fallback = EdgeAwareFilter(g, glossy=_glossy(setup[1]))
    occupied = torch.rand(5, 1, SIZE, SIZE, generator=gen) < 0.4
    imgs = torch.rand(5, 3, SIZE, SIZE, generator=gen, dtype=torch.float64) * occupied * (g.object_id >= 0)
    groups = torch.tensor([0, 0, 0, 1, 2])  # one term of three bands, then two single images

    def squash(img):  # non-linear and not the identity, so a per-band or a total-only use fails
        return img / (1 + img) + 0.1 * img.roll(1, 0)

    den = CumulativeOIDN(g, fallback, image_denoiser=squash, keep_mean=0)
    out = den(imgs, groups)
    assert den.calls == 3
    keep = fallback.interior & (imgs[:3] != 0).any(0).any(0)
    lin = fallback(imgs)
    for k in range(3):
        want = squash(imgs[: k + 1].sum(0).permute(1, 2, 0)).permute(2, 0, 1)
        torch.testing.assert_close(out[: k + 1].sum(0)[:, keep], want[:, keep], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out[:3][..., ~keep], lin[:3][..., ~keep], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out[3:], lin[3:], rtol=0, atol=0)
    same = CumulativeOIDN(g, fallback, image_denoiser=lambda img: img, keep_mean=0)(imgs, groups)
    torch.testing.assert_close(same[:3][..., keep], imgs[:3][..., keep], rtol=1e-12, atol=1e-12)
    assert float((out[:3][..., keep] - imgs[:3][..., keep]).abs().max()) > 1e-3
    mixed = CumulativeOIDN(g, fallback, image_denoiser=squash, mix=0.25, keep_mean=0)(imgs, groups)
    torch.testing.assert_close(mixed, 0.75 * out + 0.25 * lin, rtol=1e-12, atol=1e-12)
    with pytest.raises(ShapeError):
        den(imgs, groups[:3])
    with pytest.raises(ValueRangeError):
        CumulativeOIDN(g, mix=1.5)


def gaussian_within_brute(x, mask, sigma):
    """Oracle: per pixel, the Gaussian-weighted mean of ``x`` (C, H, W) over the ``mask``
    pixels within 3 sigma in x and y, one pixel at a time."""
    r = max(int(3 * sigma + 0.5), 1)
    h, w = mask.shape
    out = torch.zeros_like(x)
    for y in range(h):
        for xx in range(w):
            acc, wsum = torch.zeros(x.shape[0], dtype=x.dtype), 0.0
            for yy in range(max(y - r, 0), min(y + r + 1, h)):
                for xq in range(max(xx - r, 0), min(xx + r + 1, w)):
                    if mask[yy, xq]:
                        wt = math.exp(-0.5 * ((yy - y) ** 2 + (xq - xx) ** 2) / sigma**2)
                        acc += wt * x[:, yy, xq]
                        wsum += wt
            out[:, y, xx] = acc / wsum if wsum > 0 else 0.0
    return out


def test_cumulative_oidn_keeps_the_local_mean_of_each_prefix_sum(setup, gen):
    """``keep_mean``: each denoised prefix sum is rescaled to the noisy sum's Gaussian-window
    mean, so a denoiser that loses energy uniformly is undone exactly, and one that flattens
    the sum to its global mean (right total, wrong local means) gives the noisy sum's local
    mean: a brute-force Gaussian over the denoised pixels. Off (0), the denoiser's output is kept."""
    g = setup[3]
    fallback = EdgeAwareFilter(g, glossy=_glossy(setup[1]))
    occupied = torch.rand(3, 1, SIZE, SIZE, generator=gen) < 0.5
    imgs = torch.rand(3, 3, SIZE, SIZE, generator=gen, dtype=torch.float64) * occupied * (g.object_id >= 0)
    groups = torch.zeros(3, dtype=torch.long)
    keep = fallback.interior & (imgs != 0).any(0).any(0)
    sums = imgs.cumsum(0)

    def half(img):
        return 0.5 * img

    out = CumulativeOIDN(g, fallback, image_denoiser=half, keep_mean=2.0)(imgs, groups)
    torch.testing.assert_close(out[..., keep], imgs[..., keep], rtol=1e-12, atol=1e-12)
    off = CumulativeOIDN(g, fallback, image_denoiser=half, keep_mean=0)(imgs, groups)
    torch.testing.assert_close(off[..., keep], 0.5 * imgs[..., keep], rtol=1e-12, atol=1e-12)

    def flat(img):  # (H, W, 3): every denoised pixel set to the sum's mean over them
        return torch.where(keep[..., None], img[keep].mean(0), img)

    sigma = 1.5
    out = CumulativeOIDN(g, fallback, image_denoiser=flat, keep_mean=sigma)(imgs, groups)
    for k in range(3):
        want = gaussian_within_brute(sums[k], keep, sigma)
        torch.testing.assert_close(out[: k + 1].sum(0)[:, keep], want[:, keep], rtol=1e-9, atol=1e-12)
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueRangeError, match="keep_mean"):
            CumulativeOIDN(g, keep_mean=bad)


@needs_oidn
def test_oidn_frame_reduces_noise_of_a_flat_image(setup, gen):
    g = setup[3]
    base = torch.full((SIZE, SIZE, 3), 0.5) * (g.object_id >= 0)[..., None]
    noisy = base * (1 + 0.5 * torch.randn(SIZE, SIZE, 3, generator=gen)).clamp_min(0)
    out = oidn_frame(noisy, g)
    assert out.shape == noisy.shape
    assert float((out - base).square().mean()) < 0.5 * float((noisy - base).square().mean())


def test_regression_filter_reproduces_polynomials_and_is_linear(gen):
    """The local regression of degree k returns any image that is a polynomial of degree k in
    the pixel coordinates unchanged wherever the window lies in one object's interior (it
    removes noise, not gradients), while the weighted mean (degree 0) does not; it is linear,
    never moves values across object ids and leaves silhouette pixels as they are."""
    size = 48
    g = guide_buffers(cornell_box(size))
    yy, xx = torch.meshgrid(
        torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64), indexing="ij"
    )
    ramp = 1.0 + 0.02 * yy - 0.03 * xx
    bowl = ramp + 4e-4 * (yy - 20) ** 2 + 3e-4 * (xx - 30) ** 2 - 2e-4 * (yy - 20) * (xx - 30)
    errors = {}
    for order, img in ((1, ramp), (2, bowl), (0, ramp)):
        s = RegressionSettings(radius=3, order=order, ridge=1e-12, min_taps=0.0)
        A = RegressionFilter(g, s)
        # pixels whose whole window is interior pixels of their own object
        oid = torch.where(A.interior, g.object_id, -1)
        pad = torch.nn.functional.pad(oid[None, None].double(), (3, 3, 3, 3), value=-9.0)[0, 0]
        full = A.interior.clone()
        for dy in range(7):
            for dx in range(7):
                full &= pad[dy : dy + size, dx : dx + size] == oid.double()
        assert int(full.sum()) >= 200
        errors[order] = float((A(img) - img)[full].abs().max())
    assert errors[1] < 1e-5 and errors[2] < 1e-5  # float32 hat weights
    assert errors[0] > 1e-3  # the weighted mean flattens a ramp where the weights are lopsided
    A = RegressionFilter(g)
    x, y = torch.rand(2, 3, size, size, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(A(0.7 * x - 1.3 * y), 0.7 * A(x) - 1.3 * A(y), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(A(x)[:, ~A.interior], x[:, ~A.interior])
    floor = A.interior & (g.object_id == cornell_box(size).object_id("floor"))
    out = A(floor.double())
    assert float(out[~floor].abs().max()) == 0.0
    noise = torch.rand(size, size, generator=gen, dtype=torch.float64) * floor
    assert float(A(noise)[floor].std()) < 0.6 * float(noise[floor].std())
    with pytest.raises(ValueRangeError):
        RegressionSettings(order=3)
    with pytest.raises(ValueRangeError):
        RegressionFilter(g, AtrousSettings())
    with pytest.raises(ShapeError):
        A(torch.zeros(3, 5, 5))


def test_regression_hat_weights_are_the_per_pixel_weighted_least_squares(gen):
    """Oracle for the batched normal equations: at sample pixels the hat weights equal a
    per-pixel weighted least-squares fit solved on its own (features 1, u, v, u², v², uv,
    ridge on the non-constant ones); filters that share a GuideWeights keeping its taps (as
    the selection's candidates do) get the same weights as filters built alone."""
    size = 32
    g = guide_buffers(cornell_box(size))
    s = RegressionSettings(radius=3, order=2, sigma_space=2.5, ridge=1e-2)
    A = RegressionFilter(g, s)
    gw = GuideWeights(g)
    offsets = [(dy, dx) for dy in range(-3, 4) for dx in range(-3, 4)]
    assert A.offsets == offsets
    w_all = torch.stack(
        [
            gw.weight(dy, dx, s) * torch.exp(torch.tensor(-(dy * dy + dx * dx) / (2 * 2.5**2))).double()
            for dy, dx in offsets
        ]
    )
    pixels = torch.nonzero(A.interior)
    picks = pixels[torch.randperm(pixels.shape[0], generator=gen)[:12]]
    for y, x in picks.tolist():
        w = w_all[:, y, x]
        X = torch.tensor(
            [[1, dy / 3, dx / 3, (dy / 3) ** 2, (dx / 3) ** 2, dy * dx / 9] for dy, dx in offsets], dtype=torch.float64
        )
        M = X.T @ (w[:, None] * X) + torch.diag(torch.tensor([0.0, 1, 1, 1, 1, 1])) * s.ridge * float(w.sum())
        hat = w * (X @ torch.linalg.solve(M, torch.eye(6, dtype=torch.float64)[0]))
        torch.testing.assert_close(A.weights[:, y, x].double(), hat, rtol=1e-5, atol=1e-6)
    kept = GuideWeights(g, keep=True)
    for r, o in ((1, 1), (3, 2), (2, 0)):
        rs = RegressionSettings(radius=r, order=o)
        assert torch.equal(RegressionFilter(g, rs, guide_weights=kept).weights, RegressionFilter(g, rs).weights)
    with pytest.raises(ValueRangeError):
        RegressionFilter(g, s, glossy=[1], guide_weights=kept)


def test_mean_tensors_render_the_mean_frame(setup, halves, gen):
    """The mean record of independent runs renders the mean of their frames, full and frozen."""
    mats = setup[2]
    recs, _ = halves
    mean = mean_tensors(recs)
    assert mean.meta["spp"] == 4 and mean.meta["mean_of"] == 2
    frames = []
    for t in (*recs, mean):
        state = gen.get_state()
        R = PolynomialRenderer(t, mats, dtype=torch.float64)
        _random_edit(R, t, gen)
        gen.set_state(state)
        full = R.evaluate()
        R.freeze("back")
        frames.append((full, R()))
    for k in range(2):
        expected = (frames[0][k] + frames[1][k]) / 2
        assert _rel(frames[2][k], expected) < 1e-6
    other = precompute_polynomial(setup[0], PolynomialSettings("4,1,1", spp=1), seed=1, progress=False)
    with pytest.raises(ValueRangeError):
        mean_tensors([recs[0], other])
    with pytest.raises(ValueRangeError):
        mean_tensors([])


def _step_scene(size, gen):
    """Guides of a Cornell box, a clean image with a shadow edge the guides do not see and
    smooth shading elsewhere, and two independent noisy halves of it: (guides, clean, a, b)."""
    g = guide_buffers(cornell_box(size))
    yy, xx = torch.meshgrid(
        torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64), indexing="ij"
    )
    clean = (1.0 + 0.01 * yy) * torch.where(xx + 0.3 * yy < 0.55 * size, 1.0, 0.25)
    clean = torch.where(g.object_id >= 0, clean, 0.0).expand(3, size, size)
    a, b = (clean + 0.15 * torch.randn(3, size, size, generator=gen, dtype=torch.float64) for _ in range(2))
    return g, clean, a, b


def test_selected_regression_beats_the_fixed_window_on_a_hidden_edge(gen):
    """Known clean image with a sharp shadow edge the guides cannot see: picking the window
    per pixel from the two halves keeps the edge and still smooths the flat parts, so its
    error on the full buffer (a + b) / 2 is well below the fixed 11-pixel regression's; the
    pick is frozen (linear), never crosses object ids, and keeps silhouettes."""
    size = 64
    g, clean, a, b = _step_scene(size, gen)
    y = (a + b) / 2
    old = RegressionFilter(g)
    new = SelectedRegressionFilter(g, [(a, b)], SelectionSettings(silhouette=()))
    inner = old.interior

    def mse(img):
        return float((img - clean)[:, inner].square().mean())

    assert mse(new(y)) < 0.7 * mse(old(y)), (mse(new(y)), mse(old(y)), mse(y))
    assert mse(new(y)) < 0.4 * mse(y)  # and it denoises
    # small windows next to the edge, large ones away from it
    names = new.names
    near = inner & (((torch.arange(size)[None] + 0.3 * torch.arange(size)[:, None]) - 0.55 * size).abs() < 1.5)
    radius = torch.tensor([0 if n == "identity" else int(n[1 : n.index("o")]) for n in names])[new.pick]
    assert float(radius[near].double().mean()) < float(radius[inner & ~near].double().mean()) - 2
    x, z = torch.rand(2, 3, size, size, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(new(0.7 * x - 1.3 * z), 0.7 * new(x) - 1.3 * new(z), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(new(x)[:, ~inner], x[:, ~inner])
    floor = inner & (g.object_id == cornell_box(size).object_id("floor"))
    assert float(new(floor.double())[~floor].abs().max()) == 0.0
    with pytest.raises(ShapeError):
        SelectedRegressionFilter(g, [(a, b[:, :-1])])
    with pytest.raises(ValueRangeError):
        SelectedRegressionFilter(g, [])
    with pytest.raises(ValueRangeError):
        SelectedRegressionFilter(g, [(a, b)], RegressionSettings())
    with pytest.raises(ValueRangeError):
        SelectionSettings(candidates=())
    with pytest.raises(ValueRangeError):
        SelectionSettings(silhouette=(0,))
    with pytest.raises(ValueRangeError):
        SelectionSettings(identity=False)  # the silhouette candidates need it


def test_selected_regression_denoises_silhouette_pixels_inside_their_pair(gen):
    """Silhouette pixels (two objects in the 3 x 3 neighbourhood), which the regressions leave
    as they are, get the along-edge candidates: on a clean image that is smooth along each edge
    the pick changes most of them and lowers their error; every tap of a silhouette pixel is a
    silhouette pixel of the same signature (same objects, same side), so nothing moves between
    interior and silhouette pixels or between edges, and the filter stays linear."""
    size = 64
    g = guide_buffers(cornell_box(size))
    sig = silhouette_signature(g.object_id)
    inner = GuideWeights(g).interior
    outer = ~inner & (g.object_id >= 0)
    # clean: a constant per signature on silhouettes (a fixed coverage along each edge), smooth inside
    yy = torch.arange(size, dtype=torch.float64)[:, None].expand(size, size)
    clean = torch.where(inner, 1.0 + 0.01 * yy, 0.5 + 0.1 * (sig % 7)).expand(3, size, size)
    clean = torch.where(g.object_id >= 0, clean, 0.0)
    a, b = (clean + 0.15 * torch.randn(3, size, size, generator=gen, dtype=torch.float64) for _ in range(2))
    y = (a + b) / 2
    kept = SelectedRegressionFilter(g, [(a, b)], SelectionSettings(silhouette=()))
    new = SelectedRegressionFilter(g, [(a, b)])
    torch.testing.assert_close(kept(y)[:, ~inner], y[:, ~inner])
    changed = (new(y) - y).abs().amax(0) > 0
    assert float(changed[outer].double().mean()) > 0.5
    assert any(n.startswith("silhouette") for n in new.names)

    def mse(img):
        return float((img - clean)[:, outer].square().mean())

    assert mse(new(y)) < 0.6 * mse(y), (mse(new(y)), mse(y))
    torch.testing.assert_close(new(y)[:, inner], kept(y)[:, inner])  # interior picks unchanged
    # taps stay inside their signature's silhouette pixels
    assert float(new(inner.double())[~inner].abs().max()) == 0.0
    assert float(new((~inner).double())[inner].abs().max()) == 0.0
    for k in torch.unique(sig[outer]).tolist():
        mine = outer & (sig == k)
        assert float(new(mine.double())[~mine & outer].abs().max()) == 0.0, k
    x, z = torch.rand(2, 3, size, size, generator=gen, dtype=torch.float64)
    torch.testing.assert_close(new(0.7 * x - 1.3 * z), 0.7 * new(x) - 1.3 * new(z), rtol=1e-12, atol=1e-12)


def test_relative_selection_weighs_pilots_by_their_relative_error(gen):
    """``relative=True``: scaling one pilot pair (a brighter probe material) does not change the
    pick; without it the brighter pair decides alone."""
    size = 48
    g, _, a, b = _step_scene(size, gen)
    _, _, c, d = _step_scene(size, gen)
    c, d = c.flip(-1), d.flip(-1)  # another image: its edge elsewhere
    s = SelectionSettings(relative=True)
    one = SelectedRegressionFilter(g, [(a, b), (c, d)], s).pick
    assert torch.equal(SelectedRegressionFilter(g, [(a, b), (1e3 * c, 1e3 * d)], s).pick, one)
    raw = SelectedRegressionFilter(g, [(a, b), (1e3 * c, 1e3 * d)], SelectionSettings()).pick
    assert torch.equal(raw, SelectedRegressionFilter(g, [(c, d)], SelectionSettings()).pick)
    assert not torch.equal(raw, one)
