"""PreisachModel: output model, shapes, dtypes, continuation and input checks."""

from __future__ import annotations

import pytest
import torch

from diffaccel.hysteresis import InputRangeWarning, PreisachMesh, PreisachModel

F64 = torch.float64


def _model(**kw) -> PreisachModel:
    gen = torch.Generator().manual_seed(0)
    model = PreisachModel(PreisachMesh.triangular(10), input_range=(-5.0, 15.0), **kw)
    model.density = 0.1 + torch.rand(len(model.alpha), generator=gen, dtype=F64)
    with torch.no_grad():
        model.offset.fill_(0.3)
        model.slope.fill_(2.0)
        model.scale.fill_(0.5)
        model.output_loc.fill_(1.0)
        model.output_scale.fill_(4.0)
    return model


def test_output_is_affine_in_magnetization() -> None:
    model = _model()
    u = torch.tensor([0.0, 10.0, 2.0, 15.0, -5.0], dtype=F64)
    with torch.no_grad():
        m = model.magnetization(u)
        y = model(u)
    un = (u + 5.0) / 20.0
    torch.testing.assert_close(y, 1.0 + 4.0 * (0.3 + 2.0 * un + 0.5 * m))
    assert m.abs().max() <= 1.0


def test_density_setter_and_positivity() -> None:
    model = _model()
    with torch.no_grad():
        model.raw_density.fill_(-50.0)
    assert (model.density >= 0).all()
    with pytest.raises(ValueError, match="positive"):
        model.density = -torch.ones(len(model.alpha), dtype=F64)


@pytest.mark.parametrize("batch", [(), (3,), (2, 4)], ids=["unbatched", "B3", "B2x4"])
def test_batched_equals_loop(batch) -> None:
    model = _model()
    gen = torch.Generator().manual_seed(1)
    u = -5.0 + 20.0 * torch.rand(*batch, 25, generator=gen, dtype=F64)
    with torch.no_grad():
        y = model(u)
        s = model.states(u)
        flat = u.reshape(-1, 25)
        ref = torch.stack([model(row) for row in flat]).reshape(*batch, 25)
    assert y.shape == (*batch, 25)
    assert s.shape == (*batch, 25, len(model.alpha))
    torch.testing.assert_close(y, ref, rtol=0, atol=1e-12)  # float64 round-off


def test_float32_matches_float64() -> None:
    model = _model()
    m32 = _model().to(torch.float32)
    # inputs away from the mesh thresholds (ties would flip with round-off)
    u = torch.tensor([0.3, 10.1, 2.2, 12.3, 4.1], dtype=F64)
    with torch.no_grad():
        y64 = model(u)
        y32 = m32(u.float())
    assert y32.dtype == torch.float32
    # float32 round-off on outputs of order 10
    torch.testing.assert_close(y32.double(), y64, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("smooth", [False, True], ids=["exact", "smooth"])
def test_predict_with_history_equals_full_sequence(smooth: bool) -> None:
    model = _model()
    hist = torch.tensor([0.0, 12.0, 3.0, 8.0], dtype=F64)
    fut = torch.tensor([5.0, 14.0, -2.0], dtype=F64)
    with torch.no_grad():
        full = model(torch.cat([hist, fut]), smooth=smooth)[4:]
        pred = model.predict(fut, history=hist, smooth=smooth)
    torch.testing.assert_close(pred, full, rtol=0, atol=1e-13)


def test_continue_from_final_state() -> None:
    model = _model()
    hist = torch.tensor([0.0, 12.0, 3.0, 8.0], dtype=F64)
    fut = torch.tensor([5.0, 14.0, -2.0, 6.0], dtype=F64)
    with torch.no_grad():
        state = model.final_state(hist)
        cont = model(fut, initial_state=state)
        full = model(torch.cat([hist, fut]))[4:]
    assert state.shape == (len(model.alpha),)
    torch.testing.assert_close(cont, full, rtol=0, atol=1e-13)


def test_history_changes_prediction() -> None:
    model = _model()
    fut = torch.tensor([5.0], dtype=F64)
    with torch.no_grad():
        from_top = model.predict(fut, history=torch.tensor([15.0], dtype=F64))
        from_bottom = model.predict(fut, history=torch.tensor([-5.0], dtype=F64))
    assert float(from_top - from_bottom) > 0.01  # descending branch lies higher


@pytest.mark.parametrize(
    ("u", "match"),
    [
        (torch.tensor([0.0, float("nan")]), "NaN"),
        (torch.tensor([0.0, float("inf")]), "NaN or infinite"),
        (torch.tensor(3.0), r"\(\*B, T\)"),
    ],
    ids=["nan", "inf", "scalar"],
)
def test_bad_inputs_raise(u, match) -> None:
    model = _model()
    with pytest.raises(ValueError, match=match):
        model(u)


@pytest.mark.parametrize(
    ("beyond", "state"), [(19.0, 1.0), (-9.0, -1.0)], ids=["above", "below"]
)
def test_beyond_range_saturates_and_warns(beyond: float, state: float) -> None:
    model = _model()  # input range [-5, 15]
    u = torch.tensor([0.0, 10.0, 2.0, beyond], dtype=F64)
    with pytest.warns(InputRangeWarning, match="up to 4 \\(20 % of the range\\)"):
        y = model(u)
    # every hysteron switched: magnetization +-1; the linear term continues
    un = (beyond + 5.0) / 20.0
    expect = 1.0 + 4.0 * (0.3 + 2.0 * un + 0.5 * state)
    torch.testing.assert_close(y[-1], torch.tensor(expect, dtype=F64))
    with pytest.warns(InputRangeWarning):
        s = model.states(u)
    assert (s[-1] == state).all()


def test_training_range_check_raises() -> None:
    model = _model()
    with pytest.raises(ValueError, match="outside the model's input_range"):
        model.check_input_range(torch.tensor([0.0, 16.0]))
    model.check_input_range(torch.tensor([-5.0, 15.0]))  # the ends are inside


def test_bad_constructor_arguments_raise() -> None:
    with pytest.raises(ValueError, match="lo < hi"):
        PreisachModel(input_range=(1.0, 1.0))
    with pytest.raises(ValueError, match="initial_state must be one of"):
        PreisachModel(initial_state="sideways")
    with pytest.raises(ValueError, match="smoothing"):
        PreisachModel(smoothing=-1.0)


def test_bad_initial_state_tensor_raises() -> None:
    model = _model()
    with pytest.raises(ValueError, match="shape"):
        model(torch.tensor([1.0]), initial_state=torch.zeros(3))
    with pytest.raises(ValueError, match="learned"):
        model(torch.tensor([1.0]), initial_state="learned")


def test_mismatched_batch_of_history_raises() -> None:
    model = _model()
    with pytest.raises(RuntimeError):
        model.predict(
            torch.zeros(3, 4, dtype=F64), history=torch.zeros(2, 5, dtype=F64)
        )


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_cpu() -> None:
    model = _model()
    gpu = _model().to("cuda")
    u = torch.tensor([0.3, 10.1, 2.2, 12.3, 4.1], dtype=F64)
    with torch.no_grad():
        cpu_y = model(u)
        gpu_y = gpu(u.cuda())
        gpu_s = gpu.magnetization(u.cuda(), smooth=True)
    assert gpu_y.device.type == "cuda" and gpu_s.device.type == "cuda"
    torch.testing.assert_close(gpu_y.cpu(), cpu_y, rtol=0, atol=1e-12)


def test_symmetric_density_is_mirror_symmetric() -> None:
    gen = torch.Generator().manual_seed(5)
    model = PreisachModel(
        PreisachMesh.triangular(9), input_range=(-3.0, 3.0), symmetric=True
    )
    with torch.no_grad():
        model.raw_density.copy_(torch.randn(len(model.alpha), generator=gen))
    d = model.density
    assert torch.equal(d, d[model.mesh.mirror_index()])
    with pytest.raises(ValueError, match="no mirror image"):
        PreisachModel(PreisachMesh.from_points([0.5, 0.9], [0.1, 0.2]), symmetric=True)


def test_symmetric_major_loop_is_point_symmetric() -> None:
    # physics: with mu(a, b) = mu(-b, -a) the descending major branch is the
    # ascending one reflected through the centre: m_down(u) = -m_up(-u)
    gen = torch.Generator().manual_seed(6)
    model = PreisachModel(
        PreisachMesh.triangular(12), input_range=(-2.0, 2.0), symmetric=True
    )
    with torch.no_grad():
        model.raw_density.copy_(torch.randn(len(model.alpha), generator=gen))
    up = torch.linspace(-2.0, 2.0, 41, dtype=F64)
    with torch.no_grad():
        m = model.magnetization(torch.cat([up, up.flip(0)[1:]]))
    m_up, m_down = m[:41], m[40:].flip(0)  # both indexed by up's inputs
    torch.testing.assert_close(m_down, -m_up.flip(0), rtol=0, atol=1e-12)
    # an asymmetric density breaks it (the test can fail)
    free = PreisachModel(PreisachMesh.triangular(12), input_range=(-2.0, 2.0))
    with torch.no_grad():
        free.raw_density.copy_(torch.randn(len(free.alpha), generator=gen))
        m = free.magnetization(torch.cat([up, up.flip(0)[1:]]))
    assert float((m[40:].flip(0) + m[:41].flip(0)).abs().max()) > 1e-3
