"""Screen images: cloud-in-cell and Gaussian KDE."""

from __future__ import annotations

import math

import pytest
import torch

from diffaccel.dynamics import Screen, cic_image, kde_image, pixel_centers

F64 = torch.float64


def test_pixel_convention_rows_are_y_ascending() -> None:
    # one particle at the centre of pixel (i=3, j=1) of a 5 x 4 screen
    shape, pixel, center = (5, 4), (1e-3, 2e-3), (0.5e-3, -1e-3)
    xs, ys = pixel_centers(shape, pixel, center, dtype=F64)
    x = xs[1].reshape(1)
    y = ys[3].reshape(1)
    for image in (
        cic_image(x, y, shape, pixel, center),
        kde_image(x, y, shape, pixel, center, bandwidth=1e-5),
    ):
        assert image.argmax().item() == 3 * 4 + 1
    assert ys[3] > ys[2]  # row index grows with y
    assert xs[1].item() == pytest.approx(center[0] + (1 - 1.5) * pixel[0])


def test_cic_at_pixel_centres_equals_histogram() -> None:
    g = torch.Generator().manual_seed(0)
    shape, pixel = (8, 10), (1e-3, 1e-3)
    xs, ys = pixel_centers(shape, pixel, dtype=F64)
    i = torch.randint(0, 8, (500,), generator=g)
    j = torch.randint(0, 10, (500,), generator=g)
    image = cic_image(xs[j], ys[i], shape, pixel)
    hist = torch.zeros(shape, dtype=F64)
    hist.index_put_((i, j), torch.ones(500, dtype=F64), accumulate=True)
    torch.testing.assert_close(image, hist / 500, rtol=0, atol=1e-15)


def test_cic_sum_is_fraction_on_screen() -> None:
    g = torch.Generator().manual_seed(1)
    x = torch.randn(2000, generator=g, dtype=F64) * 5e-3
    y = torch.randn(2000, generator=g, dtype=F64) * 5e-3
    image = cic_image(x, y, (10, 10), 1e-3)
    # particles within the outer pixel centres deposit all their weight; those
    # beyond the outer centres +- one pixel deposit none
    inner = ((x.abs() <= 4.5e-3) & (y.abs() <= 4.5e-3)).double().mean()
    outer = ((x.abs() < 5.5e-3) & (y.abs() < 5.5e-3)).double().mean()
    assert inner.item() <= image.sum().item() <= outer.item()
    assert image.sum().item() < 0.6  # most of the beam misses: no renormalisation


def test_beam_missing_screen_gives_zeros_not_nan() -> None:
    x = torch.full((3, 100), 1.0, dtype=F64, requires_grad=True)  # 1 m off axis
    y = torch.zeros(3, 100, dtype=F64)
    image = cic_image(x, y, (16, 16), 1e-3)
    assert torch.equal(image, torch.zeros(3, 16, 16, dtype=F64))
    image.sum().backward()
    assert torch.equal(x.grad, torch.zeros_like(x))
    kde = kde_image(x.detach(), y, (16, 16), 1e-3)
    assert torch.equal(kde, torch.zeros(3, 16, 16, dtype=F64))


@pytest.mark.parametrize("batch", [(), (3,), (2, 2)], ids=["unbatched", "K3", "K2x2"])
def test_image_shapes(batch: tuple[int, ...]) -> None:
    x = torch.zeros(*batch, 50)
    for image in (cic_image(x, x, (6, 7), 1e-3), kde_image(x, x, (6, 7), 1e-3)):
        assert image.shape == (*batch, 6, 7)


def test_kde_equals_direct_gaussian_sum() -> None:
    g = torch.Generator().manual_seed(2)
    x = torch.randn(30, generator=g, dtype=F64) * 2e-3
    y = torch.randn(30, generator=g, dtype=F64) * 1e-3
    shape, pixel, h = (12, 14), (0.7e-3, 0.5e-3), (0.8e-3, 0.6e-3)
    xs, ys = pixel_centers(shape, pixel, dtype=F64)
    gx = torch.exp(-0.5 * ((xs[None, :] - x[:, None]) / h[0]) ** 2) / (
        math.sqrt(2 * math.pi) * h[0]
    )
    gy = torch.exp(-0.5 * ((ys[None, :] - y[:, None]) / h[1]) ** 2) / (
        math.sqrt(2 * math.pi) * h[1]
    )
    direct = torch.einsum("ni,nj->ij", gy, gx) * pixel[0] * pixel[1] / 30
    torch.testing.assert_close(
        kde_image(x, y, shape, pixel, bandwidth=h), direct, rtol=1e-12, atol=1e-15
    )


def _direct_kde(x, y, w, shape, pixel, h):
    """Dense float64 reference: the weighted Gaussian sum at every pixel centre."""
    xs, ys = pixel_centers(shape, pixel, dtype=F64)
    gx = torch.exp(-0.5 * ((xs - x[..., None]) / h) ** 2) / (math.sqrt(2 * math.pi) * h)
    gy = torch.exp(-0.5 * ((ys - y[..., None]) / h) ** 2) / (math.sqrt(2 * math.pi) * h)
    image = torch.einsum("...n,...ni,...nj->...ij", w, gy, gx)
    return image * pixel * pixel / w.sum(-1)[..., None, None]


@pytest.mark.parametrize("axis", ["rows", "columns"])
def test_kde_tiles_equal_dense_reference_on_and_off_screen(axis) -> None:
    """On the CPU each particle's kernel along the longer window side is a tile
    of pixels around its nearest pixel (particles sorted into one band per
    row or column): images and gradients equal the dense Gaussian sum's,
    including particles off the screen, with weights."""
    g = torch.Generator().manual_seed(11)
    n, pixel, h = 300, 1e-3, 1.1e-3
    wide = torch.randn(2, n, generator=g, dtype=F64) * 9e-3
    wide[:, :3] = torch.tensor([-0.023, 0.024, 0.05], dtype=F64)  # beyond the edges
    narrow = torch.randn(2, n, generator=g, dtype=F64) * 1.5e-3
    x, y, shape = (
        (narrow, wide, (40, 13)) if axis == "rows" else (wide, narrow, (13, 40))
    )
    w = torch.rand(2, n, generator=g, dtype=F64) + 0.5
    probe = torch.linspace(-1, 2, 2 * shape[0] * shape[1], dtype=F64)

    def run(render):
        xg, yg, wg = (t.clone().requires_grad_(True) for t in (x, y, w))
        image = render(xg, yg, wg)
        (image * probe.view_as(image)).sum().backward()
        return image.detach(), xg.grad, yg.grad, wg.grad

    tiles = run(lambda a, b, c: kde_image(a, b, shape, pixel, bandwidth=h, weights=c))
    dense = run(lambda a, b, c: _direct_kde(a, b, c, shape, pixel, h))
    # only kernel values below exp(-9^2 / 2) = 2.6e-18 of the peak are dropped
    torch.testing.assert_close(tiles[0], dense[0], rtol=1e-12, atol=1e-15)
    for a, b in zip(tiles[1:], dense[1:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("rows", [230, 300], ids=["uint8_keys", "int16_keys"])
def test_kde_tiles_on_long_screens_equal_dense_reference(rows) -> None:
    """Band keys (rows + 2 r bands, r = 10 here) sort as uint8 while they fit
    and as int16 beyond: both give the dense Gaussian sum's images and
    gradients, with batch dims (2, 2), one image of a single particle and one
    whose particles all miss the screen (zero image, zero gradients)."""
    g = torch.Generator().manual_seed(17)
    n, pixel, h, shape = 200, 1e-3, 1.1e-3, (rows, 7)
    x = torch.randn(2, 2, n, generator=g, dtype=F64) * 1e-3
    y = torch.randn(2, 2, n, generator=g, dtype=F64) * rows * 0.2e-3
    y[1, 0] = 1.0  # every particle 1 m above the screen
    w = torch.rand(2, 2, n, generator=g, dtype=F64) + 0.5
    w[1, 1, 1:] = 0.0  # a single particle (the others weigh nothing)
    probe = torch.linspace(-1, 2, 4 * rows * 7, dtype=F64).view(2, 2, rows, 7)

    def run(render):
        xg, yg, wg = (t.clone().requires_grad_(True) for t in (x, y, w))
        image = render(xg, yg, wg)
        (image * probe).sum().backward()
        return image.detach(), xg.grad, yg.grad, wg.grad

    tiles = run(lambda a, b, c: kde_image(a, b, shape, pixel, bandwidth=h, weights=c))
    dense = run(lambda a, b, c: _direct_kde(a, b, c, shape, pixel, h))
    assert torch.equal(tiles[0][1, 0], torch.zeros(shape, dtype=F64))
    assert not tiles[1][1, 0].any() and not tiles[2][1, 0].any()
    torch.testing.assert_close(tiles[0], dense[0], rtol=1e-12, atol=1e-15)
    for a, b in zip(tiles[1:], dense[1:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(
    "bandwidth_px", [0.07, 0.09, 0.3, 1.0, 2.6], ids=lambda s: f"{s}px"
)
@pytest.mark.parametrize("dtype", [F64, torch.float32], ids=["f64", "f32"])
def test_kde_tile_truncation_is_bounded(bandwidth_px, dtype) -> None:
    """Single particles at offsets across a pixel (tile radius
    r = floor(cut s + 1/2) pixels, tiles by powers of exp(f / s^2)): every pixel
    equals the dense Gaussian to the dtype's precision, and the pixels left out
    hold less than exp(-cut^2 / 2) of the peak (cut 9 in float64, 6 in float32).
    Bandwidths from below the one-pixel tile (0.07 px, r = 0; 0.09 px, r = 1,
    where powers come closest to overflow) to wide tiles."""
    import diffaccel.dynamics.images as images

    cut = images._KDE_CUT if dtype == F64 else images._KDE_CUT_FLOAT32
    pixel, shape = 1e-3, (31, 29)
    h = bandwidth_px * pixel
    offsets = torch.tensor([-0.4999, -0.31, 0.0, 0.27, 0.4999], dtype=F64)
    # one particle per image, x near column 16, y near row 14
    x = (offsets + 2.0) * pixel
    y = (offsets.flip(0) - 1.0) * pixel
    image = kde_image(
        x.to(dtype).unsqueeze(-1), y.to(dtype).unsqueeze(-1), shape, pixel, bandwidth=h
    ).double()
    ones = torch.ones(len(offsets), 1, dtype=F64)
    dense = _direct_kde(x.unsqueeze(-1), y.unsqueeze(-1), ones, shape, pixel, h)
    peak = (pixel / (math.sqrt(2 * math.pi) * h)) ** 2  # the kernel's maximum
    assert torch.isfinite(image).all()
    dropped = image == 0
    assert (dense[dropped] <= math.exp(-(cut**2) / 2) * peak).all()
    # float32: positions carry a round-off of ~2e-6 pixel (16 pixels from the
    # screen's edge), which moves a kernel value by its log-slope |u| / s^2
    # (u the distance in pixels) times that, plus a few ulp
    xs, ys = pixel_centers(shape, pixel, dtype=F64)
    dx, dy = (xs - x[:, None]) / pixel, (ys - y[:, None]) / pixel
    slope = (dy.abs()[:, :, None] + dx.abs()[:, None, :]) / bandwidth_px**2
    rtol = 1e-12 if dtype == F64 else 1e-6 + 4e-6 * slope
    error = (image - dense).abs()
    assert (error <= rtol * dense)[~dropped].all()


def test_kde_tile_gradcheck() -> None:
    g = torch.Generator().manual_seed(12)
    x = (torch.randn(7, generator=g, dtype=F64) * 1e-3).requires_grad_(True)
    y = (torch.randn(7, generator=g, dtype=F64) * 12e-3).requires_grad_(True)
    w = (torch.rand(7, generator=g, dtype=F64) + 0.5).requires_grad_(True)

    def f(x, y, w):
        tall = kde_image(x, y, (40, 6), 1e-3, bandwidth=(1e-3, 0.7e-3), weights=w)
        wide = kde_image(y, x, (6, 40), 1e-3, bandwidth=(0.7e-3, 1e-3), weights=w)
        return tall, wide

    # fast mode: random projections of the Jacobian (exact one: ~500 backwards)
    assert torch.autograd.gradcheck(f, (x, y, w), fast_mode=True)


def _kde_and_grads(x, y, shape, pixel, h, w, weight) -> tuple:
    """KDE image of ``(x, y)`` (weights ``w``) and the gradients of
    ``sum(image * weight)`` with respect to x, y (and w)."""
    xg, yg = x.clone().requires_grad_(True), y.clone().requires_grad_(True)
    wg = None if w is None else w.clone().requires_grad_(True)
    image = kde_image(xg, yg, shape, pixel, bandwidth=h, weights=wg)
    (image * weight.view_as(image)).sum().backward()
    grads = (xg.grad, yg.grad) + (() if wg is None else (wg.grad,))
    return (image.detach(), *grads)


@pytest.mark.parametrize("weighted", [False, True], ids=["unweighted", "weighted"])
def test_kde_full_screen_path_equals_windowed_path(monkeypatch, weighted) -> None:
    """The fixed-shape path (all images at once, no host sync; used off the CPU)
    gives the windowed path's images and gradients, here on the CPU in float64,
    with particles off the screen and chunks smaller than the beam."""
    import diffaccel.dynamics.images as images

    g = torch.Generator().manual_seed(13)
    n, shape, pixel, h = 500, (24, 30), 1e-3, (1.2e-3, 0.8e-3)
    x = torch.randn(3, n, generator=g, dtype=F64) * 6e-3
    y = torch.randn(3, n, generator=g, dtype=F64) * 4e-3 + 1e-3
    x[:, :2] = torch.tensor([-0.03, 0.02], dtype=F64)  # beyond the edges
    w = torch.rand(3, n, generator=g, dtype=F64) + 0.5 if weighted else None
    weight = torch.linspace(-1, 2, 3 * shape[0] * shape[1], dtype=F64)
    monkeypatch.setattr(images, "_FULL_CHUNK", 128)  # 4 chunks, the last partial

    def run(full: bool):
        monkeypatch.setattr(images, "_full_screen_path", lambda t: full)
        return _kde_and_grads(x, y, shape, pixel, h, w, weight)

    full, windowed = run(True), run(False)
    # windowed drops kernel values beyond 9 bandwidths (< 3e-18 of the peak)
    torch.testing.assert_close(full[0], windowed[0], rtol=1e-12, atol=1e-15)
    for a, b in zip(full[1:], windowed[1:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_kde_full_screen_gradcheck(monkeypatch) -> None:
    import diffaccel.dynamics.images as images

    monkeypatch.setattr(images, "_full_screen_path", lambda t: True)
    monkeypatch.setattr(images, "_FULL_CHUNK", 4)
    g = torch.Generator().manual_seed(14)
    x = (torch.randn(2, 7, generator=g, dtype=F64) * 2e-3).requires_grad_(True)
    y = (torch.randn(2, 7, generator=g, dtype=F64) * 2e-3).requires_grad_(True)
    w = (torch.rand(2, 7, generator=g, dtype=F64) + 0.5).requires_grad_(True)

    def f(x, y, w):
        return kde_image(x, y, (9, 8), 1e-3, bandwidth=1e-3, weights=w)

    assert torch.autograd.gradcheck(f, (x, y, w))


def test_cic_and_kde_agree_within_discretisation() -> None:
    g = torch.Generator().manual_seed(3)
    x = torch.randn(10_000, generator=g, dtype=F64) * 6e-3
    y = torch.randn(10_000, generator=g, dtype=F64) * 4e-3
    shape, pixel = (64, 64), 0.5e-3
    kde = kde_image(x, y, shape, pixel, bandwidth=0.5e-3)
    # CIC blurred with the KDE kernel differs from the KDE only by the bilinear
    # interpolation of each kernel between pixel centres: up to (1/8)(pixel/h)^2
    # ~ 12 % of one kernel's peak, averaging down over the ~50 particles a kernel
    # covers at the peak to a few % of the image peak (sampling noise is common)
    blurred = cic_image(x, y, shape, pixel, blur_sigma=0.5e-3)
    assert (blurred - kde).abs().max().item() < 0.05 * kde.max().item()
    # second moments: the KDE adds exactly h^2 to the variance, CIC adds
    # <t (1 - t)> pixel^2 = pixel^2 / 6 (bilinear spreading at uniform offsets t)
    xn = torch.randn(10_000, generator=g, dtype=F64) * 2e-3  # well inside the screen
    yn = torch.randn(10_000, generator=g, dtype=F64) * 1.5e-3
    xs, _ = pixel_centers(shape, pixel, dtype=F64)

    def var_x(image: torch.Tensor) -> torch.Tensor:
        px = image.sum(0) / image.sum()
        mean = (px * xs).sum()
        return (px * (xs - mean) ** 2).sum()

    sample = xn.var(unbiased=False)
    var_cic = var_x(cic_image(xn, yn, shape, pixel)) - sample
    var_kde = var_x(kde_image(xn, yn, shape, pixel, bandwidth=0.5e-3)) - sample
    assert var_kde.item() == pytest.approx(0.5e-3**2, rel=1e-6)
    # the average of t (1 - t) over 10k particles has ~0.3 % relative noise
    assert var_cic.item() == pytest.approx(pixel**2 / 6, rel=0.02)


def test_blur_preserves_interior_mass_and_widens() -> None:
    x = torch.zeros(1, dtype=F64)
    sharp = cic_image(x, x, (33, 33), 1e-3)
    blurred = cic_image(x, x, (33, 33), 1e-3, blur_sigma=2e-3)
    assert blurred.sum().item() == pytest.approx(1.0, rel=1e-9)
    xs, _ = pixel_centers((33, 33), 1e-3, dtype=F64)
    var = (blurred.sum(0) * xs**2).sum()
    assert var.item() == pytest.approx(4e-6, rel=1e-6)
    assert sharp.max() > blurred.max()


@pytest.mark.parametrize("weighted", [False, True], ids=["unweighted", "weighted"])
@pytest.mark.parametrize("method", ["cic", "kde"], ids=["cic", "kde"])
def test_image_gradcheck(method: str, weighted: bool) -> None:
    g = torch.Generator().manual_seed(5)
    x = (torch.randn(2, 6, generator=g, dtype=F64) * 2e-3).requires_grad_(True)
    y = (torch.randn(2, 6, generator=g, dtype=F64) * 2e-3).requires_grad_(True)
    w = (torch.rand(2, 6, generator=g, dtype=F64) + 0.5).requires_grad_(weighted)
    args = ((5, 6), (1e-3, 0.9e-3), (1e-4, -2e-4))
    if method == "cic":

        def f(x, y, w):
            return cic_image(x, y, *args, weights=w, blur_sigma=1e-3)
    else:

        def f(x, y, w):
            return kde_image(x, y, *args, bandwidth=(1.2e-3, 0.8e-3), weights=w)

    assert torch.autograd.gradcheck(f, (x, y, w))


def test_screen_image_uses_geometry() -> None:
    scr = Screen("S", shape=(4, 5), pixel_size=(1e-3, 1e-3), center=(1e-3, 0.0))
    particles = torch.zeros(2, 10, 6)
    particles[..., 0] = 1e-3  # at the screen centre
    image = scr.image(particles, "cic")
    assert image.shape == (2, 4, 5)
    assert image[0, :, 2].sum().item() == pytest.approx(1.0)


def test_screen_without_geometry_raises() -> None:
    with pytest.raises(ValueError, match="no geometry"):
        Screen("S").image(torch.zeros(3, 6))


def test_screen_unknown_method_raises() -> None:
    scr = Screen("S", shape=(4, 4), pixel_size=1e-3)
    with pytest.raises(ValueError, match="Unknown image method"):
        scr.image(torch.zeros(3, 6), method="histogram")


def _tent_image(x, y, shape, pixel):
    """Dense bilinear (tent-kernel) reference of ``cic_image``, differentiable."""
    xs, ys = pixel_centers(shape, pixel, dtype=x.dtype)
    wx = (1.0 - ((x.unsqueeze(-1) - xs) / pixel[0]).abs()).clamp(min=0.0)
    wy = (1.0 - ((y.unsqueeze(-1) - ys) / pixel[1]).abs()).clamp(min=0.0)
    return torch.einsum("...ni,...nj->...ij", wy, wx) / x.shape[-1]


@pytest.mark.parametrize("batch", [(), (3,)], ids=["unbatched", "K3"])
def test_cic_equals_dense_tent_reference_on_and_off_screen(batch) -> None:
    # positions up to 3 pixels beyond each edge: the padding ring (particles
    # within one pixel outside feed the edge; farther ones deposit nothing and
    # get zero gradient) must match the tent kernel, values and gradients
    g = torch.Generator().manual_seed(3)
    shape, pixel = (7, 9), (1e-3, 2e-3)
    x = (torch.rand(*batch, 400, generator=g, dtype=F64) - 0.5) * 15e-3
    y = (torch.rand(*batch, 400, generator=g, dtype=F64) - 0.5) * 22e-3
    x.requires_grad_(True)
    y.requires_grad_(True)
    image = cic_image(x, y, shape, pixel)
    ref = _tent_image(x, y, shape, pixel)
    torch.testing.assert_close(image, ref, rtol=1e-12, atol=1e-15)
    weight = torch.rand(shape, generator=g, dtype=F64)
    grads = torch.autograd.grad((image * weight).sum(), (x, y))
    refs = torch.autograd.grad((ref * weight).sum(), (x, y))
    for got, want in zip(grads, refs, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-12)
    far = (x.detach().abs() > 6e-3) | (y.detach().abs() > 9e-3)
    assert far.any()
    assert torch.equal(grads[0][far], torch.zeros_like(grads[0][far]))


def test_cic_huge_finite_positions_are_not_rejected() -> None:
    # the fast finiteness check (a sum) overflows here; the exact check must
    # then accept the finite positions
    x = torch.tensor([3e38, 3e38, 0.0])
    image = cic_image(x, torch.zeros(3), (5, 5), 1e-3)
    assert image.sum().item() == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="NaN or infinite"):
        cic_image(torch.tensor([0.0, float("inf")]), torch.zeros(2), (5, 5), 1e-3)
    with pytest.raises(ValueError, match="NaN or infinite"):
        kde_image(torch.zeros(2), torch.tensor([float("nan"), 0.0]), (5, 5), 1e-3)


@pytest.mark.parametrize("weighted", [False, True], ids=["unweighted", "weighted"])
@pytest.mark.parametrize("tall", [False, True], ids=["wide", "tall"])
def test_kde_particle_chunks_equal_one_chunk(monkeypatch, weighted, tall) -> None:
    """On the CPU the window kernels are evaluated and used in chunks of
    particles (cache-sized): chunks smaller than the beam and than a band (bands
    cut across chunk boundaries, the last chunk partial) give the one-chunk
    images and gradients, with unequal bandwidths and particles off the screen,
    tiles along rows (tall beam) or columns (wide beam)."""
    import diffaccel.dynamics.images as images

    g = torch.Generator().manual_seed(15)
    n, shape, pixel, h = 700, (40, 13), 1e-3, (1.1e-3, 0.9e-3)
    x = torch.randn(2, n, generator=g, dtype=F64) * 1.5e-3
    y = torch.randn(2, n, generator=g, dtype=F64) * 9e-3
    y[:, :3] = torch.tensor([-0.023, 0.024, 0.05], dtype=F64)  # beyond the edges
    if not tall:
        x, y, shape = y, x, shape[::-1]
    w = torch.rand(2, n, generator=g, dtype=F64) + 0.5 if weighted else None
    weight = torch.linspace(-1, 2, 2 * shape[0] * shape[1], dtype=F64)
    sizes = []

    def run(chunk_elements: int, min_particles: int):
        monkeypatch.setattr(images, "_CHUNK_ELEMENTS", chunk_elements)
        monkeypatch.setattr(images, "_CHUNK_MIN_PARTICLES", min_particles)
        return _kde_and_grads(x, y, shape, pixel, h, w, weight)

    chunk_particles = images._chunk_particles

    def spy(count, rows):
        sizes.append(chunk_particles(count, rows))
        counts.append(count)
        return sizes[-1]

    counts = []
    monkeypatch.setattr(images, "_chunk_particles", spy)
    one = run(2**40, 1)
    # one chunk: every particle whose tile reaches the screen (3 are beyond it)
    assert sizes == counts and all(n - 3 <= s <= n for s in sizes)
    sizes.clear()
    chunked = run(1, 97)  # 97 particles per chunk: 8 chunks, the last partial
    assert sizes and all(s == 97 for s in sizes)
    for a, b in zip(chunked, one, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)


def test_kde_particle_chunks_gradcheck(monkeypatch) -> None:
    import diffaccel.dynamics.images as images

    monkeypatch.setattr(images, "_CHUNK_ELEMENTS", 1)
    monkeypatch.setattr(images, "_CHUNK_MIN_PARTICLES", 3)
    g = torch.Generator().manual_seed(16)
    x = (torch.randn(8, generator=g, dtype=F64) * 1e-3).requires_grad_(True)
    y = (torch.randn(8, generator=g, dtype=F64) * 12e-3).requires_grad_(True)
    w = (torch.rand(8, generator=g, dtype=F64) + 0.5).requires_grad_(True)

    def f(x, y, w):
        return kde_image(x, y, (40, 6), 1e-3, bandwidth=1e-3, weights=w)

    assert torch.autograd.gradcheck(f, (x, y, w), fast_mode=True)


def _threaded_case(dtype, weighted: bool, b: int = 5):
    g = torch.Generator().manual_seed(17)
    n, shape, pixel, h = 300, (30, 24), 1e-3, (1.1e-3, 0.9e-3)
    spread = torch.linspace(1.0, 4.0, b, dtype=dtype)[:, None]
    x = torch.randn(b, n, generator=g, dtype=dtype) * 1.5e-3 * spread
    y = torch.randn(b, n, generator=g, dtype=dtype) * 6e-3 / spread
    x[:, :2] = torch.tensor([-0.05, 0.04], dtype=dtype)  # beyond the edges
    if b > 1:
        x[1] += 1.0  # the whole image off the screen
    w = torch.rand(b, n, generator=g, dtype=dtype) + 0.5 if weighted else None
    weight = torch.linspace(-1, 2, b * shape[0] * shape[1], dtype=dtype)
    return x, y, shape, pixel, h, w, weight


@pytest.mark.parametrize("weighted", [False, True], ids=["unweighted", "weighted"])
@pytest.mark.parametrize("b", [1, 5])
def test_kde_worker_threads_equal_calling_thread(monkeypatch, weighted, b) -> None:
    """Images spread over worker threads (one intra-op thread each) equal,
    bit for bit, those computed in the calling thread with one intra-op thread,
    whatever the number of workers; the caller's thread count is unchanged."""
    import diffaccel.dynamics.images as images

    monkeypatch.setattr(images, "_THREAD_MIN_PARTICLES", 1)
    x, y, shape, pixel, h, w, weight = _threaded_case(torch.float32, weighted, b)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "1")
        reference = _kde_and_grads(x, y, shape, pixel, h, w, weight)
        for workers in ("2", "3"):
            monkeypatch.setenv("DIFFACCEL_KDE_THREADS", workers)
            assert images._image_workers(x, b) == min(int(workers), b)
            threaded = _kde_and_grads(x, y, shape, pixel, h, w, weight)
            for a, r in zip(threaded, reference, strict=True):
                assert torch.equal(a, r)
            assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(threads)
    assert torch.get_num_threads() == threads


@pytest.mark.parametrize("weighted", [False, True], ids=["unweighted", "weighted"])
def test_kde_worker_threads_equal_dense_reference(monkeypatch, weighted) -> None:
    """Threaded images and gradients (float64, images off the screen, unequal
    windows) equal the full-screen reference computed without any window."""
    import diffaccel.dynamics.images as images

    monkeypatch.setattr(images, "_THREAD_MIN_PARTICLES", 1)
    monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "2")
    x, y, shape, pixel, h, w, weight = _threaded_case(F64, weighted)
    threaded = _kde_and_grads(x, y, shape, pixel, h, w, weight)
    monkeypatch.setattr(images, "_full_screen_path", lambda t: True)
    full = _kde_and_grads(x, y, shape, pixel, h, w, weight)
    torch.testing.assert_close(threaded[0], full[0], rtol=1e-12, atol=1e-15)
    for a, b in zip(threaded[1:], full[1:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)


def test_kde_worker_threads_gradcheck(monkeypatch) -> None:
    import diffaccel.dynamics.images as images

    monkeypatch.setattr(images, "_THREAD_MIN_PARTICLES", 1)
    monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "2")
    g = torch.Generator().manual_seed(18)
    x = (torch.randn(3, 7, generator=g, dtype=F64) * 1e-3).requires_grad_(True)
    y = (torch.randn(3, 7, generator=g, dtype=F64) * 12e-3).requires_grad_(True)
    w = (torch.rand(3, 7, generator=g, dtype=F64) + 0.5).requires_grad_(True)

    def f(x, y, w):
        return kde_image(x, y, (40, 6), 1e-3, bandwidth=(1e-3, 0.7e-3), weights=w)

    assert torch.autograd.gradcheck(f, (x, y, w), fast_mode=True)


def test_kde_worker_threads_when_and_how_many(monkeypatch) -> None:
    import diffaccel.dynamics.images as images

    big = torch.zeros(4, images._THREAD_MIN_PARTICLES)
    small = torch.zeros(4, images._THREAD_MIN_PARTICLES - 1)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        monkeypatch.delenv("DIFFACCEL_KDE_THREADS", raising=False)
        assert images._image_workers(big, 4) == 2
        assert images._image_workers(big, 1) == 1
        assert images._image_workers(small, 4) == 1
        with torch.profiler.profile():  # the profiler would miss the workers' ops
            assert images._image_workers(big, 4) == 1
        for setting, workers in (("0", 1), ("1", 1), ("auto", 2), ("3", 3)):
            monkeypatch.setenv("DIFFACCEL_KDE_THREADS", setting)
            assert images._image_workers(big, 4) == workers
        torch.set_num_threads(1)
        monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "auto")
        assert images._image_workers(big, 4) == 1
        monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "two")
        with pytest.raises(ValueError, match="DIFFACCEL_KDE_THREADS"):
            images._image_workers(big, 4)
    finally:
        torch.set_num_threads(threads)


def test_kde_worker_thread_failure_names_the_image(monkeypatch) -> None:
    import diffaccel.dynamics.images as images

    monkeypatch.setattr(images, "_THREAD_MIN_PARTICLES", 1)
    monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "2")

    def broken(*args):
        raise FloatingPointError("boom")

    monkeypatch.setattr(images, "_tile_forward", broken)
    x = torch.zeros(3, 5)
    with pytest.raises(RuntimeError, match="image 0 failed in a worker thread") as e:
        kde_image(x, x, (8, 8), 1e-3)
    assert isinstance(e.value.__cause__, FloatingPointError)


def test_kde_worker_threads_under_inference_mode(monkeypatch) -> None:
    import diffaccel.dynamics.images as images

    monkeypatch.setattr(images, "_THREAD_MIN_PARTICLES", 1)
    x, y, shape, pixel, h, w, _ = _threaded_case(torch.float32, True)
    monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "1")
    reference = kde_image(x, y, shape, pixel, bandwidth=h, weights=w)
    monkeypatch.setenv("DIFFACCEL_KDE_THREADS", "2")
    with torch.inference_mode():
        image = kde_image(x, y, shape, pixel, bandwidth=h, weights=w)
    torch.testing.assert_close(image, reference, rtol=1e-6, atol=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("method", ["cic", "kde"])
def test_cuda_images_and_gradients_equal_cpu(method: str) -> None:
    g = torch.Generator().manual_seed(4)
    x = torch.randn(3, 5000, generator=g, dtype=F64) * 2e-3
    y = torch.randn(3, 5000, generator=g, dtype=F64) * 1e-3
    w = torch.rand(3, 5000, generator=g, dtype=F64)
    image = cic_image if method == "cic" else kde_image
    out = {}
    for device in ("cpu", "cuda"):
        # fresh leaves on each device (``t.to("cpu")`` would be ``t`` itself,
        # and the CUDA copy of a tensor that requires grad is no leaf)
        xd, yd, wd = (t.to(device, copy=True).requires_grad_(True) for t in (x, y, w))
        img = image(xd, yd, (40, 50), 2e-4, (1e-4, 0.0), weights=wd)
        img.square().sum().backward()
        assert img.device.type == device
        out[device] = [t.detach().cpu() for t in (img, xd.grad, yd.grad, wd.grad)]
    for a, b in zip(out["cpu"], out["cuda"], strict=True):
        assert torch.allclose(a, b, rtol=1e-9, atol=1e-12 * a.abs().max().item())
