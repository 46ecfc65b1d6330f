"""Streaming a fitted model (numpy): exact relays chunk by chunk, the torch model's
predictions and band, saturation, and the saved stream spec."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from diffaccel.hysteresis import (
    InputRangeWarning,
    LaplaceBand,
    PreisachMesh,
    PreisachModel,
    StreamPredictor,
    StreamSpec,
    outside_input_range,
    predict_stream,
)
from diffaccel.hysteresis.band import _features
from diffaccel.hysteresis.states import demagnetized_state
from diffaccel.hysteresis.stream import (
    RowGroups,
    row_layout,
    start_codes,
    stream_codes,
    stream_final_state,
    stream_table,
)

F64 = torch.float64


def _random_points(m: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    a, b = rng.random(m), rng.random(m)
    alpha, beta = np.maximum(a, b), np.minimum(a, b)
    # duplicate some alphas and betas so that rows and levels are shared
    alpha[: m // 4] = alpha[m // 4 : m // 2]
    q = m // 8
    beta[m // 2 : m // 2 + q] = np.minimum(beta[:q], alpha[m // 2 : m // 2 + q])
    return alpha, beta


def _mesh(mesh: PreisachMesh) -> tuple[np.ndarray, np.ndarray]:
    return mesh.alpha.numpy(), mesh.beta.numpy()


MESHES = {
    "triangular": lambda rng: _mesh(PreisachMesh.triangular(8)),
    "refined": lambda rng: _mesh(PreisachMesh.triangular(5, refine=2, band=2)),
    "user-points": lambda rng: _random_points(60, rng),
}
INITIAL = {
    "negative": lambda a, b, rng: -np.ones_like(a),
    "positive": lambda a, b, rng: np.ones_like(a),
    "demagnetized": lambda a, b, rng: demagnetized_state(
        torch.from_numpy(a), torch.from_numpy(b)
    ).numpy(),
    "arbitrary": lambda a, b, rng: 2 * rng.random(a.shape) - 1,
}


@pytest.mark.parametrize("chunk", [1, 13, 200], ids=["1", "13", "200"])
@pytest.mark.parametrize("init", INITIAL, ids=list(INITIAL))
@pytest.mark.parametrize("mesh", MESHES, ids=list(MESHES))
def test_stream_tables_equal_relay_loop(
    mesh: str, init: str, chunk: int, relay_loop
) -> None:
    rng = np.random.default_rng(4)
    alpha, beta = MESHES[mesh](rng)
    s0 = INITIAL[init](alpha, beta, rng)
    # thresholds themselves among the inputs: ties of >= and <=
    u = rng.permutation(np.concatenate([rng.random(60), alpha[:5], beta[:5]]))
    ref = relay_loop(u, alpha, beta, s0)
    layout = row_layout(alpha, beta)
    w = rng.random(alpha.shape)
    extra = rng.standard_normal((3, alpha.size))
    # rows one by one, and merged into groups (tables of summed rows)
    groups = RowGroups(layout, cap=64)
    assert len(groups.starts) < layout.row_alpha.size
    tables = {}
    for name, lay in (("rows", layout), ("groups", groups.layout)):
        mean, band = stream_table(lay, w[None], s0), stream_table(lay, extra, s0)
        if name == "groups":
            mean, band = groups.table(mean), groups.table(band)
        tables[name] = (lay, mean[:, 0], band)
    for name, (lay, mean, band) in tables.items():
        sums, extras, last = [], [], start_codes(lay)
        np.testing.assert_array_equal(stream_final_state(last, lay, s0), s0)
        for start in range(0, u.size, chunk):
            code = stream_codes(u[start : start + chunk], lay, last)
            last = code[:, -1]
            # the codes carry the state: exact relays, no tolerance
            state = stream_final_state(last, lay, s0)
            np.testing.assert_array_equal(state, ref[start : start + chunk][-1])
            code = groups.codes(code) if name == "groups" else code
            sums.append(mean[code].sum(axis=0))
            extras.append(band[code].sum(axis=0))  # (T, 3)
        # float64 sums in another order: round-off on ~100 terms
        np.testing.assert_allclose(np.concatenate(sums), ref @ w, rtol=0, atol=1e-12)
        np.testing.assert_allclose(
            np.concatenate(extras), ref @ extra.T, rtol=0, atol=1e-12
        )


def _fitted_like(
    symmetric: bool, kind: str, seed: int
) -> tuple[PreisachModel, LaplaceBand]:
    """A model with random density and output map, and a random band."""
    gen = torch.Generator().manual_seed(seed)
    mesh = PreisachMesh.triangular(9, refine=2, band=2)
    model = PreisachModel(
        mesh, input_range=(-3.0, 5.0), initial_state=kind, symmetric=symmetric
    )
    with torch.no_grad():
        model.raw_density.copy_(torch.randn(len(mesh), generator=gen, dtype=F64))
        model.offset.fill_(0.1)
        model.slope.fill_(0.3)
        model.scale.fill_(0.7)
        model.output_loc.fill_(2.0)
        model.output_scale.fill_(1.5)
        if model.raw_initial_state is not None:
            model.raw_initial_state.copy_(torch.randn(len(mesh), generator=gen))
    directions = torch.randn(5, len(mesh) + 3, generator=gen, dtype=F64) * 0.1
    return model, LaplaceBand(directions, 0.02, calibration=1.3)


def _band_reference(model, band, u) -> torch.Tensor:
    """The band's std from dense features (T, M + 3) @ directions, float64."""
    f = _features(model, model.normalize_input(u), None)
    proj = f @ band.directions.T
    var = proj.pow(2).sum(1) + band.noise_std**2
    return model.output_scale * band.calibration * var.sqrt()


@pytest.mark.parametrize("symmetric", [False, True], ids=["plain", "symmetric"])
@pytest.mark.parametrize("kind", ["negative", "demagnetized", "learned"])
def test_predictor_equals_the_torch_model_across_chunks(symmetric, kind) -> None:
    model, band = _fitted_like(symmetric, kind, seed=1)
    gen = torch.Generator().manual_seed(2)
    # a random walk and jumps, well inside the range
    u = torch.cat(
        [
            torch.cumsum(0.4 * torch.randn(300, generator=gen, dtype=F64), 0) % 7 - 2.5,
            -3 + 8 * torch.rand(200, generator=gen, dtype=F64),
        ]
    )
    with torch.no_grad():
        whole = model(u)
        std_ref = _band_reference(model, band, u)
    spec = band.stream_spec(model)
    for chunks in ([500], [1, 7, 92, 400], [250, 250]):
        p = StreamPredictor(spec, band_dtype=np.float64)
        got = [p(part.numpy()) for part in u.split(chunks)]
        pred = np.concatenate([g[0] for g in got])
        std = np.concatenate([g[1] for g in got])
        # same float64 operations up to the order of ~200 row sums
        np.testing.assert_allclose(pred, whole.numpy(), rtol=0, atol=1e-12)
        np.testing.assert_allclose(std, std_ref.numpy(), rtol=1e-12, atol=0)
    # the float32 band of the CLI: ~1e-7 of the terms
    p = StreamPredictor(spec)
    std32 = np.concatenate([p(part.numpy())[1] for part in u.split(37)])
    np.testing.assert_allclose(std32, std_ref.numpy(), rtol=1e-5, atol=0)
    # band.std and predict_stream are this code
    with torch.no_grad():
        one = StreamPredictor(spec, band_dtype=np.float64)(u.numpy())[1]
        assert torch.equal(band.std(model, u), torch.from_numpy(one))
        streamed = torch.cat([p for p, _ in predict_stream(model, u.split(64), band)])
    torch.testing.assert_close(streamed, whole, rtol=0, atol=1e-12)


def test_beyond_the_range_saturates_with_the_linear_term_and_warns() -> None:
    model, band = _fitted_like(False, "negative", seed=3)
    u = torch.tensor([0.0, 7.0, 5.0, 9.0, 1.0, -3.0, -6.0, 0.0], dtype=F64)
    spec = band.stream_spec(model)
    p = StreamPredictor(spec, band_dtype=np.float64)
    with pytest.warns(InputRangeWarning, match=r"up to 4 \(50 % of the range\)"):
        first, _ = p(u[:4].numpy())
    with pytest.warns(InputRangeWarning, match=r"up to 3 \(37.5 % of the range\)"):
        second, std = p(u[4:].numpy())
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore", InputRangeWarning)
        whole = model(u)
        std_ref = _band_reference(model, band, u)
    np.testing.assert_allclose(np.r_[first, second], whole, rtol=0, atol=1e-12)
    np.testing.assert_allclose(std, std_ref[4:], rtol=1e-12)
    # saturated: 9 A and 7 A differ by the linear term only
    lin = (model.output_scale * model.slope).detach() * 2.0 / 8.0
    assert abs(float(first[3] - first[1]) - float(lin)) < 1e-12
    with pytest.raises(ValueError, match="NaN or infinite"):
        p(np.array([0.0, np.nan]))


def test_band_widens_beyond_the_range_with_the_slope() -> None:
    # the band used to freeze the linear term at the edge of the range: beyond
    # it the prediction moved on (slope * u_n) while its std stayed constant.
    # A band of the slope alone: std = scale * cal * sqrt((d u_n)^2 + noise^2)
    # at every input, inside the range and beyond it
    model, _ = _fitted_like(False, "negative", seed=3)
    directions = torch.zeros(1, len(model.alpha) + 3, dtype=F64)
    directions[0, 1] = 0.2
    spec = LaplaceBand(directions, 0.02, calibration=1.3).stream_spec(model)
    u = np.array([-3.0, 0.0, 5.0, 7.0, 9.0, 13.0, -7.0])  # range (-3, 5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", InputRangeWarning)
        _, std = StreamPredictor(spec, band_dtype=np.float64)(u)
    un = (u + 3.0) / 8.0
    expect = 1.5 * 1.3 * np.sqrt((0.2 * un) ** 2 + 0.02**2)
    np.testing.assert_allclose(std, expect, rtol=1e-12, atol=0)
    assert std[2] < std[3] < std[4] < std[5]
    flags = outside_input_range(u, spec.input_range)
    assert flags.tolist() == [False, False, False, True, True, True, True]
    # round-off of the affine map is not "outside"
    assert not outside_input_range(np.array([5.0 + 1e-12, -3.0 - 1e-12]), (-3, 5)).any()


def test_spec_round_trip_and_refusals() -> None:
    model, band = _fitted_like(True, "learned", seed=5)
    spec = band.stream_spec(model)
    back = StreamSpec.from_arrays(spec.to_arrays())
    u = np.linspace(-3, 5, 50) ** 2 % 8 - 3
    a, b = StreamPredictor(spec)(u), StreamPredictor(back)(u)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    plain = model.stream_spec()
    assert not plain.has_band and StreamPredictor(plain)(u)[1] is None
    arrays = spec.to_arrays()
    with pytest.raises(ValueError, match="unknown entries"):
        StreamSpec.from_arrays({**arrays, "banana": np.zeros(1)})
    with pytest.raises(ValueError, match="incomplete"):
        StreamSpec.from_arrays({k: v for k, v in arrays.items() if k != "slope"})
    with pytest.raises(ValueError, match="beta has shape"):
        StreamSpec.from_arrays({**arrays, "beta": arrays["beta"][:-1]})
    with pytest.raises(ValueError, match="non-finite"):
        StreamSpec.from_arrays({**arrays, "slope": np.array(np.inf)})
    with pytest.raises(ValueError, match="band shapes"):
        bad = {**arrays, "band_weights": arrays["band_weights"][:, :-1]}
        StreamSpec.from_arrays(bad)
