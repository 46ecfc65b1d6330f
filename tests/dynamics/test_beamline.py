"""Beamline: spec round trip, scans, screens, no hidden state, linearisation."""

from __future__ import annotations

import json

import pytest
import torch

from diffaccel.data.synthetic import AWA6D_BEAMLINES
from diffaccel.dynamics import Beamline, Element, LinearMap, Quadrupole, Screen

P0C = 43.36e6  # [eV]
F64 = torch.float64
SPEC = [
    {"type": "Quadrupole", "name": "Q1", "length": 0.1, "k1": 0.0},
    {"type": "Drift", "name": "D1", "length": 1.0},
    {"type": "Screen", "name": "SCREEN"},
]


def test_spec_round_trip_is_json() -> None:
    line = Beamline.from_spec(SPEC)
    assert line.to_spec() == SPEC
    assert json.loads(json.dumps(line.to_spec())) == SPEC
    assert line.element_names == ["Q1", "D1", "SCREEN"]
    assert isinstance(line["Q1"], Quadrupole)
    assert isinstance(line["SCREEN"], Screen)


def test_scan_matches_loop_and_does_not_mutate(make_beam) -> None:
    line = Beamline.from_spec(SPEC)
    beam = make_beam(100)
    k1 = torch.linspace(-25.0, 15.0, 5, dtype=torch.float64)
    out = line.track(beam, P0C, settings=k1.unsqueeze(-1), names=["Q1.k1"])
    assert out.shape == (5, 100, 6)
    for i, k in enumerate(k1):
        spec = [dict(SPEC[0], k1=k.item()), *SPEC[1:]]
        ref = Beamline.from_spec(spec).track(beam, P0C)
        torch.testing.assert_close(out[i], ref, rtol=1e-13, atol=1e-16)
    assert line["Q1"].k1.item() == 0.0  # the scan did not touch the beamline
    # calling again with other settings gives other (not stale) results
    again = line.track(beam, P0C, settings=-k1.unsqueeze(-1), names=["Q1.k1"])
    assert not torch.allclose(again, out)


def test_track_screens_records_particles_at_screens(make_beam) -> None:
    spec = [
        *SPEC[:2],
        {"type": "Screen", "name": "S1"},
        dict(SPEC[1], name="D2"),
        SPEC[2],
    ]
    line = Beamline.from_spec(spec)
    beam = make_beam(50)
    k1 = torch.tensor([[3.0], [-3.0]], dtype=torch.float64)
    screens = line.track_screens(beam, P0C, k1, ["Q1.k1"])
    assert list(screens) == ["S1", "SCREEN"]
    assert screens["SCREEN"].shape == (2, 50, 6)
    torch.testing.assert_close(screens["SCREEN"], line.track(beam, P0C, k1, ["Q1.k1"]))
    # S1 sits after 1.1 m, SCREEN after 2.1 m: different beams
    assert not torch.allclose(screens["S1"], screens["SCREEN"])


def test_gradient_flows_to_settings_and_particles(make_beam) -> None:
    line = Beamline.from_spec(SPEC).with_screen("SCREEN", (16, 16), 1e-3)
    beam = make_beam(200).requires_grad_(True)
    k1 = torch.tensor([[5.0], [-5.0]], dtype=torch.float64, requires_grad=True)
    at = line.track_screens(beam, P0C, k1, ["Q1.k1"])["SCREEN"]
    line["SCREEN"].image(at, "cic").square().sum().backward()
    assert beam.grad.abs().sum() > 0 and k1.grad.abs().sum() > 0


def test_with_screen_returns_new_beamline() -> None:
    line = Beamline.from_spec(SPEC)
    new = line.with_screen("SCREEN", (10, 20), (1e-3, 2e-3), (0.0, 1e-3))
    assert line["SCREEN"].shape is None
    assert new["SCREEN"].shape == (10, 20)
    assert new["SCREEN"].pixel_size == (1e-3, 2e-3)
    assert Beamline.from_spec(new.to_spec())["SCREEN"].center == (0.0, 1e-3)


def test_linearized_matches_transfer_map_and_exact_near_axis(make_beam) -> None:
    line = Beamline.from_spec(SPEC)
    k1 = torch.linspace(-20.0, 20.0, 4, dtype=torch.float64)
    lin = line.with_params({"Q1.k1": k1}).linearized(P0C)
    assert isinstance(lin["Q1..D1"], LinearMap)
    assert lin["Q1..D1"].matrix.shape == (4, 7, 7)
    beam = make_beam(30, sizes=(1e-7,) * 6)
    exact = line.track(beam, P0C, k1.unsqueeze(-1), ["Q1.k1"])
    linear = lin.track_screens(beam, P0C)["SCREEN"]
    # near the axis the exact map equals its linearisation up to second-order
    # terms: relative difference ~ amplitude (1e-7) x O(100) per unit amplitude
    assert (exact - linear).abs().max().item() < 1e-4 * linear.abs().max().item()


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        (
            [{"type": "Octupole", "name": "S"}],
            "unknown element type 'Octupole'.*Drift",
        ),
        (
            [{"type": "Drift", "name": "D", "lenght": 1.0}],
            r"unknown parameter.*\['length'\]",
        ),
        ([{"type": "Drift", "length": 1.0}], "needs a non-empty 'name'"),
        ([{"type": "Drift", "name": "D", "length": -1.0}], "length .* must be >= 0"),
        ([{"type": "Drift", "name": "D"}, {"type": "Drift", "name": "D"}], "unique"),
        ('[{"type": "Drift"}]', "decode the JSON"),
    ],
    ids=["unknown-type", "unknown-param", "no-name", "negative-length", "dup", "json"],
)
def test_bad_spec_raises(spec, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        Beamline.from_spec(spec)


@pytest.mark.parametrize(
    ("settings", "names", "match"),
    [
        (torch.zeros(3, 1), ["Q9.k1"], "no element 'Q9'"),
        (torch.zeros(3, 1), ["Q1.k2"], r"no parameter 'k2'.*'k1'"),
        (torch.zeros(3, 1), ["Q1"], "ELEMENT.parameter"),
        (torch.zeros(3, 2), ["Q1.k1"], r"\(\*K, P\)"),
        (torch.full((3, 1), float("nan")), ["Q1.k1"], "NaN"),
        (torch.zeros(3, 1), None, "both settings and names"),
    ],
    ids=["element", "param", "format", "shape", "nan", "missing-names"],
)
def test_bad_settings_raise(settings, names, match: str) -> None:
    line = Beamline.from_spec(SPEC)
    with pytest.raises(ValueError, match=match):
        line.track(torch.zeros(4, 6), P0C, settings=settings, names=names)


@pytest.mark.parametrize(
    ("particles", "p0c", "match"),
    [
        (torch.zeros(4, 7), P0C, r"\(\.\.\., N, 6\)"),
        (torch.zeros(6), P0C, r"\(\.\.\., N, 6\)"),
        (torch.full((4, 6), float("nan")), P0C, "NaN or infinite"),
        (torch.full((4, 6), float("inf")), P0C, "NaN or infinite"),
        (torch.zeros(4, 6), -1.0, "p0c"),
        (torch.zeros(4, 6), 0.0, "p0c"),
    ],
    ids=["last-dim", "1d", "nan", "inf", "negative-p0c", "zero-p0c"],
)
def test_bad_particles_raise(particles, p0c, match: str) -> None:
    line = Beamline.from_spec(SPEC)
    with pytest.raises(ValueError, match=match):
        line.track(particles, p0c)
    with pytest.raises(ValueError, match=match):
        line["D1"].track(particles, p0c)


class _Kick(Element):
    """A user element that implements only ``track`` (the required method)."""

    param_names = ("strength",)

    def __init__(self, name: str, strength: float | torch.Tensor = 0.0) -> None:
        super().__init__(name)
        self._set_param("strength", strength)

    def track(self, particles, p0c, species=None):
        unit = particles.new_tensor([0.0, 1.0, 0.0, 0.0, 0.0, 0.0])
        return particles + self.strength.to(particles)[..., None, None] * unit


def test_user_element_with_only_track_works_in_beamline(make_beam) -> None:
    line = Beamline([_Kick("K", 1e-3), Beamline.from_spec(SPEC)["D1"]])
    beam = make_beam(20)
    out = line.track(
        beam,
        P0C,
        settings=torch.tensor([[1e-3], [2e-3]], dtype=torch.float64),
        names=["K.strength"],
    )
    assert out.shape == (2, 20, 6)
    ref = line["D1"].track(_Kick("K", 2e-3).track(beam, P0C), P0C)
    torch.testing.assert_close(out[1], ref, rtol=1e-13, atol=1e-16)


@pytest.mark.parametrize("linear", [False, True], ids=["exact", "linearized"])
@pytest.mark.parametrize("method", ["cic", "kde"], ids=["cic", "kde"])
def test_screen_images_equal_track_screens_then_image(
    method: str, linear: bool, make_beam
) -> None:
    line = Beamline.from_spec(SPEC).with_screen("SCREEN", (24, 20), 1e-3)
    beam = make_beam(300).requires_grad_(True)
    k1 = torch.tensor([[10.0], [-10.0], [0.0]], dtype=torch.float64)
    if linear:
        line = line.with_params({"Q1.k1": k1[:, 0]}).linearized(P0C)
        kw = {}
    else:
        kw = {"settings": k1, "names": ["Q1.k1"]}
    images = line.screen_images(beam, P0C, method=method, **kw)["SCREEN"]
    at = line.track_screens(beam, P0C, **kw)["SCREEN"]
    ref = line["SCREEN"].image(at, method=method)
    torch.testing.assert_close(images, ref, rtol=1e-12, atol=1e-15)
    (g1,) = torch.autograd.grad(images.square().sum(), beam)
    (g2,) = torch.autograd.grad(ref.square().sum(), beam)
    torch.testing.assert_close(g1, g2, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize(
    "batched", [False, True], ids=["beam (N, 6)", "beam (K, N, 6)"]
)
def test_linear_map_track_xy_equals_track_columns(batched: bool, make_beam) -> None:
    g = torch.Generator().manual_seed(5)
    matrix = torch.randn(4, 6, 6, generator=g, dtype=torch.float64)
    m = LinearMap("M", matrix)
    beam = make_beam(50)
    if batched:
        beam = beam.expand(4, 50, 6) * torch.linspace(0.5, 2.0, 4).reshape(4, 1, 1)
    coords = tuple(beam.unbind(-1))
    x, y = m.track_xy(coords)
    full = m.track_columns(coords, torch.tensor(P0C), None)
    assert x.shape == y.shape == (4, 50)
    torch.testing.assert_close(x, full[0], rtol=1e-14, atol=1e-17)
    torch.testing.assert_close(y, full[2], rtol=1e-14, atol=1e-17)


def _awa6d_line() -> Beamline:
    """The AWA 6D dipole-on line (``data.synthetic``) with its cavity at 4 MV."""
    line = Beamline.from_spec(AWA6D_BEAMLINES["dipole_on"])
    return line.with_params({"SCAN_TDC.voltage": torch.tensor(4e6, dtype=F64)})


def _z_spy(monkeypatch, cls: type[Element]) -> list[bool]:
    """Record, per call of ``cls.track_columns``, whether it was given ``z``."""
    seen: list[bool] = []
    original = cls.track_columns

    def spy(self, coords, p0c, species):
        seen.append(coords[4] is not None)
        return original(self, coords, p0c, species)

    monkeypatch.setattr(cls, "track_columns", spy)
    return seen


def test_screen_images_track_z_only_up_to_the_last_cavity(
    monkeypatch, make_beam
) -> None:
    from diffaccel.dynamics import Dipole, Drift

    line = _awa6d_line().with_screen("DYG2", (48, 40), 1e-4)
    beam = make_beam(500, sizes=(3e-4, 1e-4, 3e-4, 1e-4, 1e-3, 2e-3))
    beam = beam.requires_grad_(True)
    k1 = torch.tensor([[-8.0], [0.0], [8.0]], dtype=F64)
    kw = {"settings": k1, "names": ["SCAN_QUAD.k1"]}
    # z is read by the cavity, so it is tracked through the quadrupole and D1,
    # and not after it (D2, the dipole and D3 feed only the screen's x and y)
    drift_z, dipole_z = _z_spy(monkeypatch, Drift), _z_spy(monkeypatch, Dipole)
    images = line.screen_images(beam, P0C, **kw)["DYG2"]
    assert drift_z == [True, False, False] and dipole_z == [False]
    # the same images and gradients as tracking every coordinate
    ref = line["DYG2"].image(line.track_screens(beam, P0C, **kw)["DYG2"])
    torch.testing.assert_close(images, ref, rtol=0, atol=0)
    (g1,) = torch.autograd.grad(images.square().sum(), beam)
    (g2,) = torch.autograd.grad(ref.square().sum(), beam)
    torch.testing.assert_close(g1, g2, rtol=1e-10, atol=1e-12 * g2.abs().max())


def test_track_columns_without_z_and_elements_that_read_it(make_beam) -> None:
    line = Beamline(list(_awa6d_line())[:-1])
    beam = make_beam(200, sizes=(3e-4, 1e-4, 3e-4, 1e-4, 1e-3, 2e-3))
    p0c = torch.tensor(P0C, dtype=F64)
    full = line.track(beam, P0C)
    cols = line.track_columns(tuple(beam.unbind(-1)), p0c, need_z=False)
    assert cols[4] is None
    for i in (0, 1, 2, 3, 5):
        torch.testing.assert_close(cols[i], full[:, i], rtol=0, atol=0)
    # an element defined elsewhere reads z unless it says otherwise, so an
    # element after the cavity gets z when one of those follows it
    assert Element.reads_z and _Kick.reads_z
    seen: list[bool] = []

    class _Probe(_Kick):
        def track_columns(self, coords, p0c, species):
            seen.append(coords[4] is not None)
            return super().track_columns(coords, p0c, species)

    tail = Beamline([*line.elements, _Probe("P", 0.0), Screen("S")])
    tail = tail.with_screen("S", (16, 16), 1e-3)
    tail.screen_images(beam, P0C)
    assert seen == [True]


def test_screen_images_with_screens_between_linear_maps(make_beam) -> None:
    spec = [*SPEC, {"type": "Drift", "name": "D2", "length": 0.5}]
    spec += [{"type": "Screen", "name": "S2"}]
    line = (
        Beamline.from_spec(spec)
        .with_screen("SCREEN", (24, 20), 1e-3)
        .with_screen("S2", (24, 20), 1e-3)
    )
    k1 = torch.tensor([10.0, -10.0], dtype=torch.float64)
    lin = line.with_params({"Q1.k1": k1}).linearized(P0C)
    assert [type(e).__name__ for e in lin] == ["LinearMap", "Screen"] * 2
    beam = make_beam(200).requires_grad_(True)
    images = lin.screen_images(beam, P0C)
    at = lin.track_screens(beam, P0C)
    for name in ("SCREEN", "S2"):
        ref = lin[name].image(at[name])
        torch.testing.assert_close(images[name], ref, rtol=1e-12, atol=1e-15)
    (g1,) = torch.autograd.grad(sum(i.square().sum() for i in images.values()), beam)
    ref = sum(lin[n].image(at[n]).square().sum() for n in ("SCREEN", "S2"))
    (g2,) = torch.autograd.grad(ref, beam)
    torch.testing.assert_close(g1, g2, rtol=1e-10, atol=1e-12)
