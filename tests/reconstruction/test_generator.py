from __future__ import annotations

import pytest
import torch

from diffaccel.reconstruction import BeamGenerator
from diffaccel.reconstruction.generator import standard_normal_samples

SCALE4 = torch.tensor([1e-3, 2e-4, 2e-3, 3e-4])


@pytest.mark.parametrize("dims", [4, 6], ids=["4d", "6d"])
def test_shape_and_4d_zero_longitudinal(dims: int) -> None:
    scale = torch.cat([SCALE4, torch.tensor([1e-3, 1e-3])])[:dims]
    g = torch.Generator().manual_seed(0)
    gen = BeamGenerator(dims, scale=scale, generator=g)
    x = gen(500, generator=g)
    assert x.shape == (500, 6)
    if dims == 4:
        assert torch.equal(x[:, 4:], torch.zeros(500, 2))
    else:
        assert (x[:, 4:].std(0) > 0).all()


def test_initial_beam_is_the_requested_gaussian() -> None:
    corr = torch.eye(4)
    corr[0, 1] = corr[1, 0] = -0.8
    offset = torch.tensor([1e-4, 0.0, -2e-4, 1e-5])
    g = torch.Generator().manual_seed(1)
    gen = BeamGenerator(4, scale=SCALE4, offset=offset, correlation=corr, generator=g)
    x = gen(10_000, generator=g).double()[:, :4]
    # sampling error of an rms: sqrt(1/(2N)) = 0.7 % at N = 10k; allow 5 of those
    assert torch.allclose(x.std(0), SCALE4.double(), rtol=0.035)
    # centroid error: sigma / sqrt(N) = 1 % of sigma; allow 5 sigma
    assert ((x.mean(0) - offset.double()).abs() < 0.05 * SCALE4.double()).all()
    r = torch.corrcoef(x.detach().T)[0, 1]
    assert abs(float(r) + 0.8) < 0.02  # sampling error of r ~ (1 - r^2)/sqrt(N)


def test_deterministic_for_a_seed() -> None:
    def run() -> torch.Tensor:
        g = torch.Generator().manual_seed(7)
        gen = BeamGenerator(4, scale=SCALE4, generator=g)
        with torch.no_grad():
            gen.mlp[-1].weight.fill_(0.1)  # make the MLP matter
        return gen(100, generator=g)

    assert torch.equal(run(), run())


def test_fresh_samples_every_call() -> None:
    g = torch.Generator().manual_seed(0)
    gen = BeamGenerator(4, scale=SCALE4, generator=g)
    assert not torch.equal(gen(100, generator=g), gen(100, generator=g))


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dims": 5, "scale": torch.ones(5)}, "dims must be 4 or 6"),
        ({"dims": 4, "scale": torch.ones(3)}, "scale must have shape"),
        ({"dims": 4, "scale": -torch.ones(4)}, "finite and > 0"),
        ({"dims": 4, "scale": torch.ones(4), "width": 0}, "width and depth"),
    ],
    ids=["dims", "scale-shape", "scale-negative", "width"],
)
def test_bad_arguments(kwargs: dict, match: str) -> None:
    dims = kwargs.pop("dims")
    with pytest.raises(ValueError, match=match):
        BeamGenerator(dims, **kwargs)


def test_quasi_random_base_samples_have_less_moment_noise() -> None:
    g = torch.Generator().manual_seed(0)
    errs = {}
    for quasi in (False, True):
        e = [
            standard_normal_samples(1024, 4, g, quasi).std(0).sub(1).abs().max()
            for _ in range(10)
        ]
        errs[quasi] = float(torch.stack(e).mean())
    # iid: ~sqrt(1/2048) = 2 %; scrambled Sobol is far better
    assert errs[True] < 0.3 * errs[False]


def test_gradients_reach_every_parameter() -> None:
    g = torch.Generator().manual_seed(0)
    gen = BeamGenerator(6, scale=torch.ones(6), generator=g).double()
    with torch.no_grad():  # the last layer starts at 0, which blocks earlier layers
        gen.mlp[-1].weight.fill_(0.1)
    x = gen(64, generator=torch.Generator().manual_seed(1))
    (x**3).sum().backward()
    for name, p in gen.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_sampling_without_gradients_in_blocks_gives_the_same_particles(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import diffaccel.reconstruction.generator as generator

    g = torch.Generator().manual_seed(2)
    gen = BeamGenerator(4, scale=SCALE4, generator=g)
    with torch.no_grad():
        for lin in gen.mlp[::2]:  # a non-trivial MLP (its last layer starts at 0)
            lin.weight.normal_(generator=g)
    whole = gen(1000, generator=torch.Generator().manual_seed(0)).detach()
    monkeypatch.setattr(generator, "_SAMPLE_CHUNK", 96)  # 11 blocks, the last short
    with torch.no_grad():
        blocks = gen(1000, generator=torch.Generator().manual_seed(0))
    # the same base samples through the same row-wise operations; BLAS may round
    # a block's products differently from the whole matrix's, never by more
    torch.testing.assert_close(blocks, whole, rtol=1e-6, atol=0.0)
    assert not torch.equal(blocks[:500], blocks[500:])  # every row its own particle


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_tanh_layer_is_tanh(dtype: torch.dtype) -> None:
    from diffaccel.reconstruction.generator import tanh_layer

    g = torch.Generator().manual_seed(0)
    h = 3 * torch.randn(4000, 6, generator=g, dtype=dtype)  # tanh saturated too
    w = torch.randn(6, 16, generator=g, dtype=dtype).requires_grad_()
    b = torch.randn(16, generator=g, dtype=dtype)
    ours = tanh_layer(h, w, b)
    ref = torch.tanh(torch.addmm(b, h, w))
    # float64: the identity 2 sigmoid(2z) - 1 = tanh z to rounding; float32:
    # the product's own rounding (|z| up to ~30, ~2e-6) plus ~1e-7 of sigmoid
    tol = 1e-14 if dtype == torch.float64 else 5e-6
    assert (ours - ref).abs().max() < tol
    (gw,) = torch.autograd.grad(ours.sum(), w)
    (gw_ref,) = torch.autograd.grad(ref.sum(), w)
    assert (gw - gw_ref).abs().max() < tol * 100 * gw_ref.abs().max()
    with torch.no_grad():  # in place on its own buffer: the same values
        assert torch.equal(tanh_layer(h, w, b), ours.detach())


def test_quadratic_features_are_unit_hermite_products() -> None:
    from diffaccel.reconstruction.generator import quadratic_features

    u = standard_normal_samples(1 << 16, 3, torch.Generator().manual_seed(0), True)
    q = quadratic_features(u.double())
    assert q.shape == (1 << 16, 6)
    # zero mean and unit variance to the Sobol sample's accuracy (~1e-3);
    # uncorrelated with each other and with the base (odd moments vanish)
    assert q.mean(0).abs().max() < 0.01
    assert (q.std(0) - 1).abs().max() < 0.01
    c = torch.cov(torch.cat([u.double(), q], 1).T)
    assert (c - torch.diag(c.diagonal())).abs().max() < 0.01


def test_6d_quadratic_term_gives_an_unbounded_curved_chirp() -> None:
    """pz = c (z^2 - 1)/sqrt(2) in base units, exactly, far into the tails,
    where the bounded tanh MLP cannot follow; 4D has none."""
    from diffaccel.reconstruction.generator import quadratic_features

    gen = BeamGenerator(6, scale=torch.ones(6), generator=torch.Generator())
    assert gen.quad.shape == (6, 21) and not gen.quad.any()  # starts at zero
    zz = [(int(i), int(j)) for i, j in zip(*torch.triu_indices(6, 6), strict=True)]
    with torch.no_grad():
        gen.quad[5, zz.index((4, 4))] = 0.8
    base = torch.zeros(5, 6)
    base[:, 4] = torch.tensor([-5.0, -3.0, 0.0, 3.0, 5.0])
    with torch.no_grad():
        x = gen.transform(base)
    expect = 0.8 * (base[:, 4] ** 2 - 1) / 2**0.5 + base[:, 5]
    torch.testing.assert_close(x[:, 5], expect)  # 13.6 at |z| = 5
    torch.testing.assert_close(
        quadratic_features(base)[:, zz.index((4, 4))], (base[:, 4] ** 2 - 1) / 2**0.5
    )
    assert not hasattr(BeamGenerator(4, scale=SCALE4), "quad")


def test_6d_generator_saved_before_the_quadratic_term_loads_as_the_same_beam() -> None:
    g = torch.Generator().manual_seed(3)
    gen = BeamGenerator(6, width=8, scale=torch.ones(6), generator=g)
    with torch.no_grad():
        gen.mlp[-1].weight.normal_(generator=g)
    old = {k: v for k, v in gen.state_dict().items() if k != "quad"}
    other = BeamGenerator(6, width=8, scale=torch.ones(6))
    other.load_state_dict(old)  # strict: the missing Q is filled with zeros
    assert not other.quad.any()
    s = torch.Generator().manual_seed(0)
    with torch.no_grad():
        assert torch.equal(
            gen(100, generator=s), other(100, generator=s.manual_seed(0))
        )
