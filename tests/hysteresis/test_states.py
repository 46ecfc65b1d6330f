"""Exact and smooth hysteron states: Preisach properties and a reference loop."""

from __future__ import annotations

import pytest
import torch

from diffaccel.hysteresis import PreisachMesh, PreisachModel
from diffaccel.hysteresis.states import (
    RowLayout,
    demagnetized_state,
    exact_magnetization,
    exact_states,
    smooth_states,
)

F64 = torch.float64


def _random_points(m: int, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    a = torch.rand(m, generator=gen, dtype=F64)
    b = torch.rand(m, generator=gen, dtype=F64)
    alpha, beta = torch.maximum(a, b), torch.minimum(a, b)
    # duplicate some alphas and betas so that rows and levels are shared
    alpha[: m // 4] = alpha[m // 4 : m // 2]
    beta[m // 2 : m // 2 + m // 8] = beta[: m // 8].clamp(max=alpha[m // 2 :][: m // 8])
    return alpha, beta


MESHES = {
    "triangular": lambda g: (lambda m: (m.alpha, m.beta))(PreisachMesh.triangular(8)),
    "refined": lambda g: (lambda m: (m.alpha, m.beta))(
        PreisachMesh.triangular(5, refine=2, band=2)
    ),
    "user-points": lambda g: _random_points(60, g),
}
INITIAL = {
    "negative": lambda a, b, g: -torch.ones_like(a),
    "positive": lambda a, b, g: torch.ones_like(a),
    "demagnetized": lambda a, b, g: demagnetized_state(a, b),
    "arbitrary": lambda a, b, g: 2 * torch.rand(a.shape, generator=g, dtype=F64) - 1,
}


@pytest.mark.parametrize("init", INITIAL, ids=list(INITIAL))
@pytest.mark.parametrize("mesh", MESHES, ids=list(MESHES))
def test_vectorised_equals_relay_loop(mesh: str, init: str, relay_loop) -> None:
    gen = torch.Generator().manual_seed(1)
    alpha, beta = MESHES[mesh](gen)
    s0 = INITIAL[init](alpha, beta, gen)
    # random inputs plus exact threshold values (ties: u == alpha switches up)
    u = torch.cat([torch.rand(50, generator=gen, dtype=F64), alpha[:5], beta[:5]])
    u = u[torch.randperm(u.numel(), generator=gen)]
    ref = torch.from_numpy(relay_loop(u, alpha, beta, s0))
    states = exact_states(u, alpha, beta, s0)
    assert torch.equal(states, ref)  # relays are exact: no tolerance
    w = torch.rand(alpha.shape, generator=gen, dtype=F64)
    m = exact_magnetization(u, RowLayout(alpha, beta), w, s0)
    # summation order differs: float64 round-off on sums of ~100 terms
    torch.testing.assert_close(m, ref @ w, rtol=0, atol=1e-12)


def test_batched_equals_loop_over_batch(relay_loop) -> None:
    gen = torch.Generator().manual_seed(2)
    mesh = PreisachMesh.triangular(6)
    layout = RowLayout(mesh.alpha, mesh.beta)
    u = torch.rand(2, 3, 30, generator=gen, dtype=F64)
    s0 = 2 * torch.rand(2, 3, len(mesh), generator=gen, dtype=F64) - 1
    w = torch.rand(len(mesh), generator=gen, dtype=F64)
    m = exact_magnetization(u, layout, w, s0)
    s = exact_states(u, mesh.alpha, mesh.beta, s0, layout)
    assert m.shape == (2, 3, 30) and s.shape == (2, 3, 30, len(mesh))
    for i in range(2):
        for j in range(3):
            ref = torch.from_numpy(relay_loop(u[i, j], mesh.alpha, mesh.beta, s0[i, j]))
            assert torch.equal(s[i, j], ref)
            torch.testing.assert_close(m[i, j], ref @ w, rtol=0, atol=1e-12)


def _model(n: int = 12, **kw) -> PreisachModel:
    gen = torch.Generator().manual_seed(3)
    model = PreisachModel(PreisachMesh.triangular(n), input_range=(0.0, 1.0), **kw)
    model.density = 0.1 + torch.rand(len(model.alpha), generator=gen, dtype=F64)
    return model


@pytest.mark.parametrize("points", [2, 10, 1000], ids=["2pts", "10pts", "1000pts"])
def test_rate_independence_exact(points: int) -> None:
    model = _model()
    tail = torch.tensor([0.35, 0.6, 0.2, 0.45], dtype=F64)
    coarse = torch.cat([torch.tensor([0.05, 0.95], dtype=F64), tail])
    fine = torch.cat([torch.linspace(0.05, 0.95, points, dtype=F64), tail])
    with torch.no_grad():
        m_coarse = model.magnetization(coarse)[-5:]
        m_fine = model.magnetization(fine)[-5:]
    # m is in [-1, 1] (full scale 2); the spec asks for 1e-6 of full scale
    torch.testing.assert_close(m_fine, m_coarse, rtol=0, atol=2e-6)


@pytest.mark.parametrize("points", [2, 10, 1000], ids=["2pts", "10pts", "1000pts"])
def test_rate_independence_smooth(points: int) -> None:
    model = _model(smoothing=0.05)
    tail = torch.tensor([0.35, 0.6, 0.2, 0.45], dtype=F64)
    coarse = torch.cat([torch.tensor([0.05, 0.95], dtype=F64), tail])
    fine = torch.cat([torch.linspace(0.05, 0.95, points, dtype=F64), tail])
    with torch.no_grad():
        m_coarse = model.magnetization(coarse, smooth=True)[-5:]
        m_fine = model.magnetization(fine, smooth=True)[-5:]
    # rate independent by construction: equal up to float64 round-off, far
    # below the smoothing width's effect (~0.05 of full scale)
    torch.testing.assert_close(m_fine, m_coarse, rtol=0, atol=1e-12)


def test_smooth_tends_to_exact() -> None:
    # thresholds of an n-cell mesh sit at least h/3 from multiples of h; with a
    # width of h/60 every relay is >= 20 widths from its switching point, where
    # the logistic tail is e^-20 ~ 2e-9
    n = 10
    h = 1.0 / n
    mesh = PreisachMesh.triangular(n)
    gen = torch.Generator().manual_seed(4)
    u = torch.randint(0, n + 1, (40,), generator=gen).to(F64) * h
    s0 = -torch.ones(len(mesh), dtype=F64)
    exact = exact_states(u, mesh.alpha, mesh.beta, s0)
    smooth = smooth_states(u, mesh.alpha, mesh.beta, s0, width=h / 60, start=0.0)
    torch.testing.assert_close(smooth, exact, rtol=0, atol=1e-7)


@pytest.mark.parametrize(
    "turn",
    [[0.2, 0.7, 0.35], [0.9, 0.3, 0.62]],
    ids=["rising-after-minimum", "falling-after-maximum"],
)
def test_smooth_states_bounded_and_continuous_at_turning_points(turn) -> None:
    mesh = PreisachMesh.triangular(8)
    s0 = demagnetized_state(mesh.alpha, mesh.beta)
    u_turn = torch.tensor(turn[:2], dtype=F64)
    eps = 1e-9
    step = eps if turn[1] < turn[0] else -eps  # reverse direction after turn[1]
    u = torch.cat([u_turn, u_turn[-1:] + step, torch.tensor(turn[2:], dtype=F64)])
    s = smooth_states(u, mesh.alpha, mesh.beta, s0, width=0.05, start=0.5)
    assert s.min() >= -1.0 and s.max() <= 1.0
    # an input step of 1e-9 after a turning point moves states by O(eps / w),
    # not by a jump: the segment formula is anchored at the turning state
    torch.testing.assert_close(s[2], s[1], rtol=0, atol=1e-6)
    # and the state did change along the new segment (the test can fail)
    assert (s[3] - s[1]).abs().max() > 1e-2


def test_wiping_out() -> None:
    # an excursion to a new maximum erases the memory of smaller extrema
    model = _model()
    with_minor = torch.tensor([0.0, 0.7, 0.3, 0.6, 0.4, 0.9], dtype=F64)
    direct = torch.tensor([0.0, 0.9], dtype=F64)
    assert torch.equal(model.final_state(with_minor), model.final_state(direct))
    with_minor_down = torch.tensor([1.0, 0.2, 0.6, 0.3, 0.5, 0.1], dtype=F64)
    direct_down = torch.tensor([1.0, 0.1], dtype=F64)
    assert torch.equal(
        model.final_state(with_minor_down), model.final_state(direct_down)
    )


def test_return_point_memory() -> None:
    model = _model()
    history = torch.tensor([0.0, 0.8, 0.3], dtype=F64)
    loop = torch.tensor([0.45, 0.6, 0.35, 0.5, 0.3], dtype=F64)
    s_before = model.final_state(history)
    s_after = model.final_state(torch.cat([history, loop]))
    assert torch.equal(s_before, s_after)
    # and continuing below the return point behaves as if the loop never was
    cont = torch.tensor([0.1, 0.65], dtype=F64)
    with torch.no_grad():
        a = model.predict(cont, history=history)
        b = model.predict(cont, history=torch.cat([history, loop]))
    assert torch.equal(a, b)


def test_congruent_minor_loops() -> None:
    # minor loops between the same reversal inputs are congruent whatever the
    # history that led to them (Mayergoyz): equal up to a constant offset
    model = _model()
    cycle = torch.tensor([0.2, 0.3, 0.4, 0.5, 0.4, 0.3, 0.2, 0.35, 0.5], dtype=F64)
    h1 = torch.tensor([0.0, 0.95, 0.2], dtype=F64)
    h2 = torch.tensor([0.0, 0.6, 0.2], dtype=F64)
    with torch.no_grad():
        m1 = model.predict(cycle, history=h1) - model.predict(cycle, history=h1)[0]
        m2 = model.predict(cycle, history=h2) - model.predict(cycle, history=h2)[0]
        # the loops are not trivially the same: the offsets differ
        off = model.predict(cycle, history=h1)[0] - model.predict(cycle, history=h2)[0]
    assert abs(float(off)) > 1e-3
    torch.testing.assert_close(m1, m2, rtol=0, atol=1e-12)  # float64 round-off


@pytest.mark.parametrize(
    ("kind", "u0", "expected"),
    [("negative", 0.0, -1.0), ("positive", 1.0, 1.0), ("demagnetized", 0.5, 0.0)],
    ids=["negative", "positive", "demagnetized"],
)
def test_initial_states(kind: str, u0: float, expected: float) -> None:
    # u0 is where each initial state sits: nothing switches there
    model = PreisachModel(PreisachMesh.triangular(10), initial_state=kind)
    with torch.no_grad():
        m = model.magnetization(torch.tensor([u0], dtype=F64))
    # the triangular mesh is mirror symmetric: demagnetized m = 0 exactly
    # up to float64 round-off
    torch.testing.assert_close(
        m, torch.tensor([expected], dtype=F64), atol=1e-12, rtol=0
    )


def test_learned_initial_state_gets_gradients() -> None:
    model = PreisachModel(PreisachMesh.triangular(6), initial_state="learned")
    u = torch.tensor([0.3, 0.5, 0.4], dtype=F64)
    model.magnetization(u)[-1].backward()
    grad = model.raw_initial_state.grad
    # at the last step, hysterons with beta < 0.3 and alpha > 0.5 were never
    # switched: they keep the learned state and carry gradient; others have none
    kept = (model.beta < 0.3) & (model.alpha > 0.5)
    assert kept.any()
    assert (grad[kept].abs() > 0).all() and (grad[~kept] == 0).all()


def test_gradcheck_smooth_wrt_density_and_inputs() -> None:
    mesh = PreisachMesh.triangular(4)
    s0 = -torch.ones(len(mesh), dtype=F64)
    u = torch.tensor([0.1, 0.62, 0.47, 0.83, 0.31, 0.55], dtype=F64, requires_grad=True)
    gen = torch.Generator().manual_seed(5)
    w = (0.5 + torch.rand(len(mesh), generator=gen, dtype=F64)).requires_grad_(True)

    def fn(u_, w_):
        s = smooth_states(u_, mesh.alpha, mesh.beta, s0, width=0.1, start=0.0)
        return s @ w_ / w_.sum()

    assert torch.autograd.gradcheck(fn, (u, w))


def test_gradcheck_model_smooth_wrt_raw_density_and_inputs() -> None:
    model = PreisachModel(PreisachMesh.triangular(4), input_range=(0.0, 10.0))
    u = torch.tensor([1.0, 6.2, 4.7, 8.3, 3.1], dtype=F64, requires_grad=True)
    raw = model.raw_density.detach().clone().requires_grad_(True)

    def fn(u_, raw_):
        return torch.func.functional_call(
            model, {"raw_density": raw_}, (u_,), {"smooth": True}
        )

    assert torch.autograd.gradcheck(fn, (u, raw))


def test_gradcheck_exact_wrt_weights_and_initial() -> None:
    mesh = PreisachMesh.triangular(5)
    layout = RowLayout(mesh.alpha, mesh.beta)
    gen = torch.Generator().manual_seed(6)
    u = torch.rand(2, 12, generator=gen, dtype=F64)
    w = torch.rand(len(mesh), generator=gen, dtype=F64).requires_grad_(True)
    s0 = (torch.rand(len(mesh), generator=gen, dtype=F64) - 0.5).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda w_, s_: exact_magnetization(u, layout, w_, s_), (w, s0)
    )
