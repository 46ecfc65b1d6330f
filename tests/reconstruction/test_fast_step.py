"""The training fast path equals the reference functions it replaces."""

from __future__ import annotations

import pytest
import torch

from diffaccel.reconstruction import BeamGenerator, ScreenForwardModel
from diffaccel.reconstruction.forward import LinearScreenImages
from diffaccel.reconstruction.generator import (
    FlatGenerator,
    shifted_sobol_normals,
    sobol_integers,
)
from diffaccel.reconstruction.losses import (
    ImagePenalty,
    RelativeEntropy,
    gaussian_entropy,
    gaussian_prior_term,
    image_penalty,
    off_screen_allowance,
)
from diffaccel.reconstruction.training import FlatAdam

SCALE = torch.tensor([1e-3, 1e-4, 2e-3, 3e-4], dtype=torch.float64)


def _beam_with_halo(n: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    x = torch.randn(n, 4, generator=g, dtype=torch.float64) * SCALE
    x[:, 1] += 0.05 * x[:, 0]  # correlated
    x[: n // 50] *= 30.0  # a far halo that the robust weights must ignore
    return x


@pytest.mark.parametrize("radius", [4.0, None], ids=["robust", "plain"])
def test_relative_entropy_equals_entropy_minus_prior(radius: float | None) -> None:
    x = _beam_with_halo(3000)
    pm = torch.tensor([1e-5, 0.0, 0.0, 1e-6], dtype=torch.float64)
    ps = 3 * SCALE
    xa = x.clone().requires_grad_()
    ref = gaussian_entropy(xa, radius=radius, scale=SCALE)
    ref = ref - gaussian_prior_term(xa - pm, ps)
    ref.backward()
    xb = x.clone().requires_grad_()
    spec = RelativeEntropy(3000, SCALE, pm, ps, radius)
    value, moments = spec(xb)
    value.backward()
    # same float64 algebra in another order: round-off ~1e-12 of O(1) values
    assert abs(float(value.detach() - ref.detach())) < 1e-9
    assert torch.allclose(xb.grad, xa.grad, rtol=1e-9, atol=1e-9 * xa.grad.abs().max())
    entropy, rms = spec.entropy_and_rms(
        float(value.detach()), moments.reshape(-1).tolist()
    )
    h = gaussian_entropy(x, radius=radius, scale=SCALE)
    assert abs(entropy - float(h)) < 1e-9
    # rms from E[x^2] - E[x]^2: cancellation of the (small) means, float64
    assert torch.allclose(torch.tensor(rms, dtype=torch.float64), x.std(0), rtol=1e-12)


def test_relative_entropy_refuses_a_second_call_before_backward() -> None:
    spec = RelativeEntropy(100, SCALE, torch.zeros(4), 3 * SCALE)
    x = _beam_with_halo(100).requires_grad_()
    first, _ = spec(x)
    spec(x)  # overwrites the work buffers the first call's backward needs
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        first.backward()


def test_linear_screen_images_equal_images_linear(gpsr_like_forward) -> None:
    fwd, maps = gpsr_like_forward
    g = torch.Generator().manual_seed(1)
    n = 2000
    x = torch.randn(n, 4, generator=g) * torch.tensor([1e-3, 1e-4, 1e-3, 1e-4])
    x6 = torch.cat([x, torch.zeros(n, 2)], 1).requires_grad_()
    ref = fwd.images_linear(x6, maps)
    weights = torch.randn(ref.shape, generator=g)
    (ref * weights).sum().backward()
    xa = x.clone().requires_grad_()
    img = LinearScreenImages(fwd, maps, n, 4)(xa)
    (img * weights).sum().backward()
    # float32 kernels summed in another order: ~1e-6 relative
    assert (img - ref).abs().max() < 1e-5 * ref.abs().max()
    assert (xa.grad - x6.grad[:, :4]).abs().max() < 1e-4 * x6.grad.abs().max()


def test_flat_generator_gradient_is_autograds() -> None:
    g = torch.Generator().manual_seed(0)
    gen = BeamGenerator(6, width=8, depth=3, scale=torch.ones(6), generator=g)
    gen = gen.double()
    with torch.no_grad():
        for p in gen.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    net = FlatGenerator(gen, 20, quasi_random=False)
    base = torch.randn(20, 6, generator=g, dtype=torch.float64)
    from diffaccel.reconstruction.generator import _GeneratorFn

    assert torch.autograd.gradcheck(
        lambda flat: _GeneratorFn.apply(flat, base, net), (net.flat,)
    )
    assert torch.equal(_GeneratorFn.apply(net.flat, base, net), gen.transform(base))


def test_flat_adam_equals_torch_adam() -> None:
    g = torch.Generator().manual_seed(0)
    a = torch.randn(50, generator=g, dtype=torch.float64)
    b = a.clone().requires_grad_()
    ours = FlatAdam(a)
    ref = torch.optim.Adam([b], lr=1e-2, foreach=False)
    for i in range(5):
        grad = torch.randn(50, generator=g, dtype=torch.float64)
        ours.step(grad, lr=1e-2 * (i + 1))
        b.grad = grad.clone()
        ref.param_groups[0]["lr"] = 1e-2 * (i + 1)
        ref.step()
    assert torch.equal(a, b.detach())


def test_shifted_sobol_normals_are_fresh_and_balanced() -> None:
    pts = sobol_integers(4096, 4)
    g = torch.Generator().manual_seed(0)
    z1, z2 = shifted_sobol_normals(pts, g), shifted_sobol_normals(pts, g)
    assert not torch.equal(z1, z2)
    for z in (z1, z2):  # QMC: moments far better than i.i.d.'s 1/sqrt(N) = 1.6 %
        assert z.mean(0).abs().max() < 2e-3
        assert (z.std(0) - 1).abs().max() < 5e-3


@pytest.fixture
def gpsr_like_forward():
    from diffaccel.dynamics import Beamline, Drift, Quadrupole, Screen

    line = Beamline(
        [
            Quadrupole(name="Q1", length=0.1, k1=0.0),
            Drift(name="D1", length=2.0),
            Screen(name="S", shape=(48, 40), pixel_size=(1e-4, 1.2e-4)),
        ]
    )
    fwd = ScreenForwardModel(line, ["Q1.k1"], 1e8, blur_pixels=1.0)
    maps = fwd.transfer_maps(torch.linspace(-10, 10, 5)[:, None])
    return fwd, maps


@pytest.mark.parametrize("kind", ["kl", "l1"])
def test_image_penalty_equals_mean_of_image_penalty(kind: str) -> None:
    g = torch.Generator().manual_seed(0)
    meas = torch.rand(4, 24, 20, generator=g) ** 4
    meas[:, :6] = 0.0  # measured zeros: the 1e-12 floor
    meas[1, :, 0] += 0.02  # mass at the border: an off-screen allowance
    meas = meas / meas.sum((-2, -1), keepdim=True)
    allow = off_screen_allowance(meas)
    # near the measurement (ratios m / s of order 1, so that every term of the
    # gradient shows at the tolerance below)
    sim = meas + torch.rand(4, 24, 20, generator=g) / 480
    sim[:, :, :5] = 0.0  # simulated zeros: the clamp passes no gradient there
    sim = sim / sim.sum((-2, -1), keepdim=True)
    sim[0] *= 0.7  # 30 % off the screen: penalised
    sim[2] *= 1e-7  # total below the 1e-6 floor of the normalisation
    sa = sim.clone().requires_grad_()
    ref = image_penalty(sa, meas, kind, allow).mean()
    weights = torch.randn((), generator=g)
    (ref * weights).backward()
    sb = sim.clone().requires_grad_()
    ours = ImagePenalty(meas, kind, allow, weight=1 / 4)(sb)
    (ours * weights).backward()
    # float32 sums in another order: ~1e-7 relative
    assert abs(float(ours.detach() - ref.detach())) < 1e-6 * abs(float(ref))
    # per image: the gradient of the 1e-7 image is ~1e7 times the others'
    err = (sb.grad - sa.grad).abs().amax((-2, -1))
    assert (err < 1e-5 * sa.grad.abs().amax((-2, -1))).all()
