"""Beamlines to and from cheetah 0.8.4 Segments and lattice files.

Tracking agreement: every coordinate to 1e-9 of its range at the exit (float64,
2 % energy spread), cheetah with its exact ("drift_kick_drift") tracking.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path

import cheetah
import pytest
import torch

from diffaccel.dynamics import (
    Beamline,
    Dipole,
    Drift,
    LinearMap,
    Quadrupole,
    RFCavity,
    Screen,
    Sextupole,
    Solenoid,
    TransverseDeflectingCavity,
    bmad_to_cheetah,
    cheetah_to_bmad,
    energy_to_p0c,
    p0c_to_energy,
)
from diffaccel.dynamics.cheetah_interop import (
    LatticeConversionWarning,
    LatticeImportError,
)

F64 = torch.float64
P0C = 43.36e6  # [eV]
SPREAD = (1e-3, 1e-4, 1e-3, 1e-4, 1e-3, 2e-2)
HERE = Path(__file__).parent / "lattices"
AWA_LTE = HERE / "awa_6d.lte"
AWA_BMAD = HERE / "awa_6d.bmad"
AWA_SPEC = json.loads((HERE / "awa_6d_spec.json").read_text())


def _t(v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


def _track_cheetah(segment, beam: torch.Tensor) -> torch.Tensor:
    particles = torch.ones(beam.shape[0], 7, dtype=F64)
    particles[:, :6] = bmad_to_cheetah(beam, P0C)
    out = segment.track(cheetah.ParticleBeam(particles, energy=p0c_to_energy(_t(P0C))))
    return cheetah_to_bmad(out.particles, energy_to_p0c(out.energy))


def _rel(theirs: torch.Tensor, ours: torch.Tensor) -> float:
    d = (theirs - ours).abs().amax(0) / ours.abs().amax(0).clamp(min=1e-30)
    return d.max().item()


def _exact_tracking(segment) -> None:
    """Switch cheetah's elements to the tracking diffaccel does."""
    for e in segment.flattened().elements:
        if isinstance(e, cheetah.Drift | cheetah.Quadrupole | cheetah.Dipole):
            e.tracking_method = "drift_kick_drift"


def _diagnostic_segment():
    """A cheetah 6D diagnostic line with every element both codes track alike."""
    return cheetah.Segment(
        [
            cheetah.Quadrupole(
                _t(0.11),
                _t(8.0),
                misalignment=torch.tensor([1e-4, -2e-4], dtype=F64),
                tilt=_t(0.02),
                name="Q1",
                dtype=F64,
            ),
            cheetah.Drift(_t(0.7), name="D1", dtype=F64),
            cheetah.TransverseDeflectingCavity(
                _t(0.1),
                _t(3e6),
                _t(0.01),
                _t(1.3e9),
                tilt=_t(math.pi / 2),
                name="TDC",
                dtype=F64,
            ),
            cheetah.Drift(_t(0.4), name="D2", dtype=F64),
            cheetah.Dipole(
                _t(0.3), _t(-0.35), dipole_e2=_t(-0.35), name="B1", dtype=F64
            ),
            cheetah.Marker(name="M1"),
            cheetah.Drift(_t(0.7), name="D3", dtype=F64),
            cheetah.Screen(
                resolution=(60, 40),
                pixel_size=torch.tensor([2e-4, 3e-4], dtype=F64),
                name="SCR",
                dtype=F64,
            ),
        ]
    )


def test_segment_tracking_agrees_with_cheetah(make_beam) -> None:
    segment = _diagnostic_segment()
    _exact_tracking(segment)
    line = Beamline.from_cheetah(segment)
    assert [type(e).__name__ for e in line] == [
        "Quadrupole",
        "Drift",
        "TransverseDeflectingCavity",
        "Drift",
        "Dipole",
        "Drift",
        "Drift",
        "Screen",
    ]
    beam = make_beam(500, sizes=SPREAD)
    rel = _rel(_track_cheetah(segment, beam), line.track(beam, P0C))
    assert rel < 1e-9, rel


def test_round_trip_keeps_every_common_element(make_beam) -> None:
    line = Beamline(
        [
            Quadrupole("Q", 0.1, 5.0, tilt=0.1, dx=1e-4, dy=2e-4),
            Drift("D", 0.5),
            Solenoid("S", 0.2, 3.0, dx=1e-4),
            Sextupole("X", 0.1, 40.0, tilt=0.2),
            TransverseDeflectingCavity("T", 0.1, 1e6, 2.856e9, 0.3, tilt=0.4),
            RFCavity("C", 0.3, 2e6, 1.3e9, 0.0),
            Dipole("B", 0.3, 0.2, 0.05, 0.1, tilt=0.1),
            LinearMap("M", torch.eye(6, dtype=F64) + 0.01, 0.2),
            Screen("S1", (40, 60), (1e-4, 2e-4), (1e-5, -2e-5)),
            Screen("S2"),
        ]
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", LatticeConversionWarning)
        back = Beamline.from_cheetah(line.to_cheetah(p0c=P0C), p0c=P0C)
    ours, theirs = line.to_spec(), back.to_spec()
    for a, b in zip(ours, theirs, strict=True):
        assert a.keys() == b.keys(), (a, b)
        for k, v in a.items():
            if isinstance(v, float):
                assert math.isclose(v, b[k], rel_tol=1e-12, abs_tol=1e-15), (k, a, b)
            elif k == "matrix":
                torch.testing.assert_close(
                    torch.tensor(b[k]), torch.tensor(v), rtol=1e-12, atol=1e-14
                )
            else:
                assert v == b[k], (k, a, b)


def test_unsupported_elements_are_named_not_dropped() -> None:
    segment = cheetah.Segment(
        [
            cheetah.Drift(_t(1.0), name="D1", dtype=F64),
            cheetah.HorizontalCorrector(_t(0.1), _t(1e-3), name="HC", dtype=F64),
            cheetah.Dipole(_t(0.3), _t(0.1), k1=_t(1.0), name="BQ", dtype=F64),
        ]
    )
    with pytest.raises(LatticeImportError, match=r"HC: .*BQ: combined-function.*"):
        Beamline.from_cheetah(segment)
    with pytest.warns(LatticeConversionWarning, match="HC|BQ"):
        drifted = Beamline.from_cheetah(segment, approximate="drift")
    assert [type(e).__name__ for e in drifted] == ["Drift"] * 3
    assert float(drifted.length) == pytest.approx(1.4)
    with pytest.warns(LatticeConversionWarning, match="linear map"):
        linear = Beamline.from_cheetah(segment, approximate="linear", p0c=P0C)
    # the corrector's linear map carries its kick as the offset
    assert linear["HC"].transfer_map(P0C)[1, 6].item() == pytest.approx(1e-3)


@pytest.mark.parametrize("line", ["dipole_off", "dipole_on"])
def test_awa_elegant_lattice_gives_the_spec_maps(line: str, make_beam) -> None:
    """The hand-written elegant AWA line equals the reference data's beamline."""
    ours = Beamline.from_lattice(AWA_LTE, line=line)
    spec = Beamline.from_spec(AWA_SPEC[line])
    assert [type(e) for e in ours] == [type(e) for e in spec]
    names = ["SCAN_QUAD.k1", "SCAN_TDC.voltage"]
    k1 = torch.linspace(-12, 12, 5, dtype=F64)
    settings = torch.stack(
        torch.meshgrid(k1, torch.tensor([0.0, 4e6], dtype=F64), indexing="ij"), -1
    ).reshape(-1, 2)
    r_ours = ours.with_params(
        {n: settings[:, i] for i, n in enumerate(names)}
    ).transfer_map(P0C)
    r_spec = spec.with_params(
        {n: settings[:, i] for i, n in enumerate(names)}
    ).transfer_map(P0C)
    torch.testing.assert_close(r_ours, r_spec, rtol=1e-13, atol=1e-15)
    beam = make_beam(400, sizes=SPREAD)
    out_ours = ours.track(beam, P0C, settings, names)
    out_spec = spec.track(beam, P0C, settings, names)
    torch.testing.assert_close(out_ours, out_spec, rtol=1e-13, atol=1e-16)


def test_awa_bmad_lattice_maps_the_crab_cavity(make_beam) -> None:
    """cheetah's Bmad converter has no crab_cavity: it is mapped on top of it."""
    ours = Beamline.from_lattice(AWA_BMAD, screens=["DYG2"])
    spec = Beamline.from_spec(AWA_SPEC["dipole_on"])
    assert isinstance(ours["SCAN_TDC"], TransverseDeflectingCavity)
    assert float(ours["SCAN_TDC"].frequency) == 1.3e9
    assert float(ours["SCAN_TDC"].tilt) == pytest.approx(math.pi / 2)
    beam = make_beam(300, sizes=SPREAD)
    names = ["SCAN_QUAD.k1", "SCAN_TDC.voltage"]
    settings = torch.tensor([[-6.0, 4e6], [9.0, 4e6]], dtype=F64)
    torch.testing.assert_close(
        ours.track(beam, P0C, settings, names),
        spec.track(beam, P0C, settings, names),
        rtol=1e-13,
        atol=1e-16,
    )


def test_elegant_file_tracking_agrees_with_cheetah(tmp_path, make_beam) -> None:
    """A line cheetah's elegant converter reads without loss (RFDF at cheetah's
    default frequency, no tilt): ours and cheetah's tracking of the same file."""
    lte = tmp_path / "line.lte"
    lte.write_text(
        "Q1: QUAD, L=0.11, K1=7.5\n"
        "D1: DRIF, L=0.73\n"
        "TDC: RFDF, L=0.1, VOLTAGE=3e6, FREQUENCY=2.856e9, PHASE=90\n"
        "D2: DRIF, L=0.47\n"
        "B1: CSBEND, L=0.3, ANGLE=-0.35, E1=0.0, E2=-0.35\n"
        "D3: DRIF, L=0.73\n"
        'SCR: WATCH, FILENAME="scr.sdds"\n'
        "DIAG: LINE=(Q1, D1, TDC, D2, B1, D3, SCR)\n"
    )
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        segment = cheetah.Segment.from_elegant(str(lte), "diag", dtype=F64)
    _exact_tracking(segment)
    ours = Beamline.from_lattice(lte)
    assert ours.element_names == ["Q1", "D1", "TDC", "D2", "B1", "D3", "SCR"]
    beam = make_beam(500, sizes=SPREAD)
    rel = _rel(_track_cheetah(segment, beam), ours.track(beam, P0C))
    assert rel < 1e-9, rel


def test_elegant_losses_of_cheetahs_converter_are_repaired(tmp_path) -> None:
    """RFDF FREQUENCY/TILT (dropped by cheetah) and SOLE KS (read as 0)."""
    lte = tmp_path / "line.lte"
    lte.write_text(
        "TDC: RFDF, L=0.1, VOLTAGE=1e6, FREQUENCY=1.3e9, PHASE=95, TILT=0.5\n"
        "S1: SOLE, L=0.2, KS=1.5\n"
        "L1: LINE=(TDC, S1)\n"
    )
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        line = Beamline.from_lattice(lte)
    assert not [w for w in caught if "frequency" in str(w.message).lower()]
    tdc = line["TDC"]
    assert float(tdc.frequency) == 1.3e9
    assert float(tdc.tilt) == 0.5
    assert float(tdc.phase) == pytest.approx(math.radians(5.0))
    assert float(line["S1"].ks) == 1.5


def test_attributes_cheetah_ignores_are_reported(tmp_path) -> None:
    lte = tmp_path / "line.lte"
    lte.write_text("Q1: QUAD, L=0.1, K1=2.0, DX=1e-3\nL1: LINE=(Q1)\n")
    with pytest.warns(LatticeConversionWarning, match=r"line.lte.*dx"):
        Beamline.from_lattice(lte)


def test_unknown_lattice_elements_are_refused_by_name(tmp_path) -> None:
    lte = tmp_path / "line.lte"
    lte.write_text(
        "Q1: QUAD, L=0.1, K1=2.0\nU1: UKICKMAP, L=0.5\nD1: DRIF, L=1\n"
        "L1: LINE=(Q1, U1, D1)\n"
    )
    with pytest.raises(LatticeImportError, match="U1: ukickmap"):
        Beamline.from_lattice(lte)
    with pytest.warns(LatticeConversionWarning, match="U1"):
        line = Beamline.from_lattice(lte, approximate="drift")
    assert isinstance(line["U1"], Drift)
    assert float(line["U1"].length) == 0.5


def test_start_end_and_repeated_names(tmp_path) -> None:
    lte = tmp_path / "line.lte"
    lte.write_text(
        "D: DRIF, L=0.5\nQ1: QUAD, L=0.1, K1=2.0\nQ2: QUAD, L=0.1, K1=-2.0\n"
        "M: MARK\nL1: LINE=(D, Q1, D, Q2, D, M)\n"
    )
    line = Beamline.from_lattice(lte)
    assert line.element_names == ["D", "Q1", "D_2", "Q2", "D_3", "M"]
    part = Beamline.from_lattice(lte, start="q1", end="Q2")
    assert part.element_names == ["Q1", "D_2", "Q2"]
    assert isinstance(Beamline.from_lattice(lte, screens=["M"])["M"], Screen)
    with pytest.raises(LatticeImportError, match="--end 'Q9'"):
        Beamline.from_lattice(lte, end="Q9")


def test_bad_files_get_one_line_errors(tmp_path) -> None:
    with pytest.raises(LatticeImportError, match="no such lattice file"):
        Beamline.from_lattice(tmp_path / "missing.lte")
    odd = tmp_path / "line.xyz"
    odd.write_text("")
    with pytest.raises(LatticeImportError, match="unknown lattice suffix"):
        Beamline.from_lattice(odd)


def test_lattice_json_round_trip(tmp_path, make_beam) -> None:
    segment = _diagnostic_segment()
    _exact_tracking(segment)
    path = tmp_path / "line.json"
    segment.to_lattice_json(str(path))
    line = Beamline.from_lattice(path)
    assert line.to_spec() == Beamline.from_cheetah(segment).to_spec()


def test_accelerating_cavities(tmp_path) -> None:
    """An lcavity on crest changes the reference energy: refused by name; a
    Bmad rfcavity (absent from cheetah's converter) is an RFCavity."""
    bmad = tmp_path / "line.bmad"
    bmad.write_text(
        "d1: drift, l = 0.5\n"
        "acc: lcavity, l = 1.0, rf_frequency = 1.3e9, voltage = 1e7, phi0 = 0.0\n"
        "rf: rfcavity, l = 0.3, rf_frequency = 2.856e9, voltage = 2e6, phi0 = 0.25\n"
        "l1: line = (d1, acc, rf)\nuse, l1\n"
    )
    with pytest.raises(LatticeImportError, match="ACC: accelerating cavity changes"):
        Beamline.from_lattice(bmad)
    line = Beamline.from_lattice(bmad, start="RF")
    assert isinstance(line["RF"], RFCavity)
    assert float(line["RF"].phase) == pytest.approx(math.pi / 2)
    with pytest.raises(LatticeImportError, match="RF: the reference particle gains"):
        line.to_cheetah()


def test_dipole_fringe_field_agrees_with_cheetah(make_beam) -> None:
    """Bmad's linear fringe (gap, fringe integral), as cheetah tracks it."""
    segment = cheetah.Segment(
        [
            cheetah.Dipole(
                _t(0.3),
                _t(0.25),
                dipole_e1=_t(0.1),
                dipole_e2=_t(0.15),
                gap=_t(0.03),
                gap_exit=_t(0.02),
                fringe_integral=_t(0.5),
                fringe_integral_exit=_t(0.4),
                tracking_method="drift_kick_drift",
                name="B1",
                dtype=F64,
            )
        ]
    )
    line = Beamline.from_cheetah(segment)
    assert float(line["B1"].hgap) == pytest.approx(0.015)
    beam = make_beam(500, sizes=SPREAD)
    rel = _rel(_track_cheetah(segment, beam), line.track(beam, P0C))
    assert rel < 1e-9, rel
    # the linear map is the Jacobian of the tracking at the reference
    jac = torch.autograd.functional.jacobian(
        lambda u: line.track(u.unsqueeze(0), P0C)[0], torch.zeros(6, dtype=F64)
    )
    torch.testing.assert_close(
        line.transfer_map(P0C)[:6, :6], jac, rtol=1e-10, atol=1e-12
    )


# ---- Ocelot cells (``Beamline.from_ocelot``) --------------------------------------


@pytest.fixture(scope="module")
def ocelot():
    """The ocelot package (imported here: its import compiles with numba)."""
    import ocelot

    return ocelot


def _cell(ocelot) -> list:
    """An Ocelot diagnostic line: quadrupole, bend, screen."""
    return [
        ocelot.Quadrupole(l=0.11, k1=8.0, eid="Q1"),
        ocelot.Drift(l=0.7, eid="D1"),
        ocelot.Drift(l=0.4, eid="D2"),
        ocelot.SBend(l=0.3, angle=-0.35, e2=-0.35, eid="B1"),
        ocelot.Drift(l=0.7, eid="D3"),
        ocelot.Monitor(eid="BSC_SCREEN"),
    ]


def test_ocelot_cell_tracks_as_cheetah_tracks_it(ocelot, make_beam) -> None:
    from cheetah.converters import ocelot as ocelot_converter

    cell = _cell(ocelot)
    line = Beamline.from_ocelot(cell)
    assert [type(e).__name__ for e in line] == [
        "Quadrupole",
        "Drift",
        "Drift",
        "Dipole",
        "Drift",
        "Screen",
    ]
    # cheetah tracks a sextupole to second order and a solenoid by its linear
    # map (docs/lattices.md): mapped, not tracked here
    sext = Beamline.from_ocelot([ocelot.Sextupole(l=0.1, k2=20.0, eid="S1")])["S1"]
    assert isinstance(sext, Sextupole) and float(sext.k2) == pytest.approx(20.0)
    sol = Beamline.from_ocelot([ocelot.Solenoid(l=0.2, k=1.5, eid="SOL")])["SOL"]
    assert isinstance(sol, Solenoid) and float(sol.ks) == pytest.approx(3.0)
    # a cavity at its zero crossing (90 deg from crest): cheetah cannot track it
    rf = ocelot.Cavity(l=0.2, v=4e-3, freq=2.856e9, phi=90.0, eid="RF")
    cavity = Beamline.from_ocelot([rf])["RF"]
    assert isinstance(cavity, RFCavity)
    assert float(cavity.voltage) == pytest.approx(4e6)  # Ocelot: GV
    segment = cheetah.Segment(
        [
            ocelot_converter.convert_element(
                e, sanitize_name=False, dtype=torch.float64
            )
            for e in cell
        ]
    ).double()  # the converter leaves a cavity's buffers in float32
    _exact_tracking(segment)
    beam = make_beam(500, sizes=SPREAD)
    rel = _rel(_track_cheetah(segment, beam), line.track(beam, P0C))
    assert rel < 1e-9, rel


def test_ocelot_elements_cheetah_does_not_map_are_named_not_dropped(ocelot) -> None:
    cell = [ocelot.Drift(l=1.0, eid="D1"), ocelot.Multipole(kn=[0.0, 0.1], eid="MP")]
    with pytest.raises(LatticeImportError, match=r"MP: ocelot\.Multipole"):
        Beamline.from_ocelot(cell)
    # cheetah's converter would make a deflector an accelerating cavity
    tds = ocelot.TDCavity(l=0.1, freq=1.3e9, v=3e-3, eid="TDS")
    with pytest.raises(LatticeImportError, match=r"TDS: ocelot\.TDCavity"):
        Beamline.from_ocelot([tds])
    with pytest.warns(LatticeConversionWarning, match="MP"):
        line = Beamline.from_ocelot(cell, approximate="drift")
    assert [type(e).__name__ for e in line] == ["Drift", "Drift"]
    with pytest.raises(LatticeImportError, match="only become drifts"):
        Beamline.from_ocelot(cell, approximate="linear", p0c=P0C)
    # what cheetah maps but diffaccel lacks is refused as for a Segment
    with pytest.raises(LatticeImportError, match="HC"):
        Beamline.from_ocelot([ocelot.Hcor(l=0.1, angle=1e-3, eid="HC")])
