"""Beam statistics against known Gaussian beams and linear transport."""

from __future__ import annotations

import math

import pytest
import torch

from diffaccel.dynamics import (
    ELECTRON,
    Quadrupole,
    centroid,
    covariance,
    emittance,
    emittance_4d,
    emittance_6d,
    normalized_emittance,
    rms_sizes,
    twiss,
)

F64 = torch.float64
N = 10_000
# relative sampling error of a second moment ~ sqrt(2 / N) = 1.4 %; allow 5 of those
SAMPLING = 5 * math.sqrt(2 / N)


def _correlated_beam(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(6, 6, generator=g, dtype=F64) * 0.3 + torch.eye(6, dtype=F64)
    scale = torch.diag(torch.tensor([1e-3, 1e-4, 2e-3, 2e-4, 1e-3, 1e-3], dtype=F64))
    chol = scale @ a
    cov = chol @ chol.T
    z = torch.randn(N, 6, generator=g, dtype=F64)
    return z @ chol.T, cov


def test_covariance_of_sample() -> None:
    beam, cov = _correlated_beam()
    est = covariance(beam)
    rel = (est - cov).abs() / (
        cov.diagonal().sqrt()[:, None] * cov.diagonal().sqrt()[None, :]
    )
    assert rel.max().item() < SAMPLING
    assert centroid(beam).abs().max().item() < 5 * 2e-3 / math.sqrt(N)
    torch.testing.assert_close(rms_sizes(beam), est.diagonal().sqrt())


def test_emittances_of_sample() -> None:
    beam, cov = _correlated_beam(1)
    for plane, i in (("x", 0), ("y", 2), ("z", 4)):
        expected = torch.det(cov[i : i + 2, i : i + 2]).sqrt()
        assert emittance(beam, plane).item() == pytest.approx(
            expected.item(), rel=SAMPLING
        )
    assert emittance_4d(beam).item() == pytest.approx(
        torch.det(cov[:4, :4]).sqrt().item(), rel=2 * SAMPLING
    )
    assert emittance_6d(beam).item() == pytest.approx(
        torch.det(cov).sqrt().item(), rel=3 * SAMPLING
    )


def test_emittance_invariant_under_linear_transport(make_beam) -> None:
    beam = make_beam(2000, sizes=(1e-3, 1e-4, 1e-3, 1e-4, 0.0, 0.0))
    k1 = torch.linspace(-20.0, 20.0, 4, dtype=F64)
    r = Quadrupole("Q", 0.3, k1).transfer_map(43e6)[..., :6, :6]
    out = beam @ r.transpose(-1, -2)
    # symplectic (det 1) 2x2 blocks: emittance conserved to round-off
    torch.testing.assert_close(
        emittance(out, "x"), emittance(beam, "x").expand(4), rtol=1e-10, atol=0
    )
    torch.testing.assert_close(
        emittance_4d(out), emittance_4d(beam).expand(4), rtol=1e-10, atol=0
    )


def test_normalized_emittance_and_twiss() -> None:
    beam, _ = _correlated_beam(2)
    p0c = 100e6
    eps = emittance(beam, "x")
    assert normalized_emittance(beam, p0c, "x").item() == pytest.approx(
        (eps * p0c / ELECTRON.mass_ev).item(), rel=1e-14
    )
    tw = twiss(beam, "x")
    cov = covariance(beam)
    assert tw.beta.item() == pytest.approx((cov[0, 0] / eps).item(), rel=1e-12)
    assert tw.alpha.item() == pytest.approx((-cov[0, 1] / eps).item(), rel=1e-12)
    # Courant-Snyder identity
    assert (tw.beta * tw.gamma - tw.alpha**2).item() == pytest.approx(1.0, rel=1e-10)


def test_batched_statistics_shapes() -> None:
    beam = torch.randn(3, 2, 100, 6, dtype=F64)
    assert covariance(beam).shape == (3, 2, 6, 6)
    assert emittance(beam, "y").shape == (3, 2)
    assert emittance_6d(beam).shape == (3, 2)
    assert twiss(beam, "x").beta.shape == (3, 2)


def test_float32_emittance_is_accurate() -> None:
    beam, _ = _correlated_beam(3)
    ref = emittance(beam, "x")
    # float64 accumulation inside: float32 input only loses its own round-off
    assert emittance(beam.float(), "x").item() == pytest.approx(ref.item(), rel=1e-5)
    assert emittance(beam.float(), "x").dtype == torch.float32


def test_weights_equal_duplicates() -> None:
    beam, _ = _correlated_beam(4)
    small = beam[:50]
    w = torch.ones(50, dtype=F64)
    w[:10] = 2.0
    dup = torch.cat((small, small[:10]))
    torch.testing.assert_close(
        covariance(small, w), covariance(dup), rtol=1e-12, atol=0
    )


@pytest.mark.parametrize(
    "fn",
    [emittance, emittance_4d, emittance_6d, lambda p: twiss(p, "y").alpha],
    ids=["emittance", "emittance_4d", "emittance_6d", "twiss_alpha"],
)
def test_statistics_gradcheck(fn) -> None:
    beam, _ = _correlated_beam(5)
    p = (beam[:8] * 1e3).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (p,))


def test_bad_plane_raises() -> None:
    with pytest.raises(ValueError, match="plane"):
        emittance(torch.zeros(5, 6), "w")
