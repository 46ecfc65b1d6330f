"""Stored benchmark results: ``benchmarks/_meta.py``'s ``store`` and each
benchmark's ``headline``.

``store`` writes ``benchmarks/results/NAME.json`` in the form that
``docs/benchmarks_page.py`` reads. Every benchmark script has a
``headline(result)`` and a ``--store`` flag; each ``headline`` is checked
against the figures of the benchmark's stored result: on the full result the
stored file carries (written by ``--store``), and on a small result with the
keys its script prints and the stored numbers where the stored file has no full
result. The benchmarks themselves are not run.
"""

from __future__ import annotations

import argparse
import ast
import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "benchmarks"
RESULTS = BENCH / "results"


def _module(path: Path) -> ModuleType:
    # the scripts import their helpers (_meta, _sixd, each other) by name
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    spec = importlib.util.spec_from_file_location(path.stem, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    # importing Xopt (xopt_hysteresis.py) sets torch's default dtype to
    # float64 for the whole process; the tests after this one expect float32
    dtype = torch.get_default_dtype()
    try:
        spec.loader.exec_module(module)
    finally:
        torch.set_default_dtype(dtype)
    return module


def _scripts() -> list[Path]:
    return sorted(BENCH.glob("[!_]*.py"))


def _stored(name: str) -> dict:
    return json.loads((RESULTS / f"{name}.json").read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def meta() -> ModuleType:
    return _module(BENCH / "_meta.py")


def _fake_result() -> dict:
    return {"name": "fake", "seconds": 1.25, "ratio": 7.5, "std": float("nan")}


def _fake_headline(result: dict) -> dict[str, str]:
    return {"wall time": f"{result['seconds']:.2f} s", "ratio": f"{result['ratio']}x"}


def test_store_writes_the_page_format(meta, tmp_path, monkeypatch) -> None:
    page = _module(ROOT / "docs" / "benchmarks_page.py")
    path = meta.store(_fake_result(), _fake_headline, note="a note", results=tmp_path)
    assert path == tmp_path / "fake.json"
    stored = json.loads(path.read_text())
    assert stored["name"] == "fake"
    assert stored["headline"] == {"wall time": "1.25 s", "ratio": "7.5x"}
    assert stored["note"] == "a note"
    prov = stored["provenance"]
    assert set(prov) == {"command", "machine", "date", "git_commit"}
    assert prov["command"].startswith("python ")
    assert isinstance(prov["machine"], str) and "cores" in prov["machine"]
    assert prov["date"].endswith(" UTC") and prov["git_commit"]
    # the full result under its own key, with the run's provenance
    assert stored["result"]["seconds"] == 1.25
    assert stored["result"]["std"] is None  # standard JSON: NaN as null
    assert "NaN" not in path.read_text()
    assert stored["result"]["provenance"]["date"] == prov["date"]
    # the page renders it: one table row per figure, the provenance line, the note
    monkeypatch.setattr(page, "RESULTS", tmp_path)
    lines = page._section("fake", BENCH / "cli_help.py")
    assert "| wall time | 1.25 s |" in lines and "| ratio | 7.5x |" in lines
    assert any(line.startswith("Command: `python ") for line in lines)
    assert "Note: a note." in lines


def test_store_replaces_the_previous_result_and_checks_its_input(
    meta, tmp_path
) -> None:
    meta.store(_fake_result(), _fake_headline, results=tmp_path)
    second = {**_fake_result(), "seconds": 2.0}
    meta.store(second, _fake_headline, name="other", results=tmp_path)
    meta.store(second, _fake_headline, results=tmp_path)
    assert json.loads((tmp_path / "fake.json").read_text())["headline"][
        "wall time"
    ] == ("2.00 s")
    assert json.loads((tmp_path / "other.json").read_text())["name"] == "other"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fake.json", "other.json"]
    with pytest.raises(ValueError, match="no 'name'"):
        meta.store({"seconds": 1.0}, _fake_headline, results=tmp_path)
    with pytest.raises(ValueError, match="headline"):
        meta.store(_fake_result(), lambda r: {}, results=tmp_path)
    with pytest.raises(ValueError, match="headline"):
        meta.store(_fake_result(), lambda r: {"figure": [1, 2]}, results=tmp_path)


def test_emit_prints_as_before_and_stores_only_when_asked(
    meta, tmp_path, capsys
) -> None:
    out = tmp_path / "out.json"
    results = tmp_path / "results"
    results.mkdir()
    meta.emit(_fake_result(), out, headline=_fake_headline, results=results)
    printed = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert printed["seconds"] == 1.25 and "provenance" in printed
    assert json.loads(out.read_text()) == printed
    assert not list(results.iterdir())
    meta.emit(
        _fake_result(), headline=_fake_headline, store_result=True, results=results
    )
    captured = capsys.readouterr()
    assert json.loads(captured.out.strip().splitlines()[-1])["ratio"] == 7.5
    assert "stored" in captured.err
    assert json.loads((results / "fake.json").read_text())["headline"]["ratio"] == (
        "7.5x"
    )
    # a skipped run keeps the stored result
    meta.emit(
        {"name": "fake", "skipped": "no data"},
        headline=_fake_headline,
        store_result=True,
        results=results,
    )
    assert "not stored: no data" in capsys.readouterr().err
    assert json.loads((results / "fake.json").read_text())["result"]["ratio"] == 7.5


def test_machine_line_and_span(meta) -> None:
    info = {"cpu": "CPU X", "cores": 2, "load_avg_1min": 1.234, "python": "3.12.1"}
    assert meta.machine_line(info) == "CPU X, 2 cores, load 1.2, Python 3.12.1"
    assert meta.machine_line("as written") == "as written"
    assert meta.span([0.05, 0.44, 0.2], ".2f") == "0.05-0.44"
    assert meta.span([3.0, 3.0], ".1f") == "3.0"


def test_the_store_flag(meta) -> None:
    parser = argparse.ArgumentParser()
    meta.add_store_flag(parser)
    assert parser.parse_args([]).store is False
    assert parser.parse_args(["--store"]).store is True


@pytest.mark.parametrize("path", _scripts(), ids=lambda p: p.stem)
def test_every_benchmark_has_a_headline_and_the_store_flag(path: Path) -> None:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert "headline" in functions, path.name
    calls = {
        n.func.id
        for n in ast.walk(tree)
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)
    }
    assert "add_store_flag" in calls, path.name
    has_full = "result" in _stored(path.stem)
    assert has_full or path.stem in FAKES, f"add a result for {path.stem} to FAKES"


def _case(ratio: float) -> dict:
    return {"ratio": ratio, "alarms": 0}


def _beams6d() -> dict:
    def beam(l1: float, fails: list[str] | None = None) -> dict:
        worst = {"dipole_off": l1 - 0.01, "dipole_on": l1}
        return {"fails": fails or [], "stats": {"held_out_relative_l1_worst": worst}}

    family = ["chirp_curved", "chirp_negative", "chirp_weak_tilted"]
    beams = {name: beam(0.08) for name in family}
    beams |= {f"draw31{i:02d}_0": beam(0.08) for i in range(2)}
    beams |= {name: beam(0.08) for name in ("double_horn", "wide")}
    beams |= {name: beam(0.09) for name in ("shared", "correlated", "gaussian_coupled")}
    beams["nonlinear_ypy"] = beam(0.1149, ["rms_pz", "emit_6d"])
    beams["nonlinear_ypy"]["runs"] = [
        {"misses": {}},
        {"misses": {"emit_6d": {"error": -0.158, "in_reported_std": -0.28}}},
        {
            "misses": {
                "rms_pz": {"error": 0.053, "in_reported_std": 0.13},
                "emit_6d": {"error": -0.248, "in_reported_std": -0.39},
            }
        },
    ]
    return {
        "seeds": [0, 1, 2],
        "beams": beams,
        "fails": {"nonlinear_ypy": ["rms_pz", "emit_6d"]},
    }


#: per benchmark: a small result with the keys its script prints and the
#: numbers of its stored result
FAKES: dict[str, dict] = {
    "gpu_checks": {
        "steps": {
            "6144": {"step_time_s": [0.00058, 0.00063], "limit_s": 0.003},
            "100000": {"step_time_s": [0.00145, 0.00148], "limit_s": 0.005},
        },
        "process": {"ratios": [5.26, 6.13], "target": 5.0},
        "sixd": {"wall_s": 33.0, "fails": []},
    },
    "alarms": {
        "good_fits": 20,
        "false_alarms": 0,
        "bad_fits": 8,
        "detected": 8,
        "limits": {"k1_scale_wrong": []},
        "cases": {
            "quad_length_doubled": {
                "expected": "inconsistent_scans",
                "alarms": ["inconsistent_scans"],
            },
            "mislabelled_setting": {
                "expected": "outlier_setting",
                "alarms": ["moment_miss", "outlier_setting"],
            },
            "pedestal": {"expected": "background", "alarms": ["background"]},
            "good_single_gaussian_0": {"alarms": []},
        },
    },
    "bo_hysteresis": {
        "gp": {"median_final_best": 0.070},
        "hgp": {"median_final_best": 0.039},
        "hgp_measured": {"median_final_best": 0.021},
        "seeds": 10,
        "steps": 50,
    },
    "calibration": {
        "pooled": {
            "n": 44,
            "coverage_2sigma": 42 / 44,
            "median_rel_std_constrained": 0.005,
        },
        "datasets": {f"d{i}": {"dims": 6} for i in range(4)},
    },
    "cli_help": {
        "acceptance_max_ratio": 1.3,
        "ratio_help_vs_import_torch": 0.037,
        "ratio_reconstruct_help_vs_import_torch": 1.03,
    },
    "design": {
        "designed": {
            "n_settings": 5,
            "median_emit_rel_std": 0.0086,
            "median_emit_abs_rel_err": 0.0041,
        },
        "even": {
            "n_settings": 10,
            "median_emit_rel_std": 0.0085,
            "median_emit_abs_rel_err": 0.0044,
        },
    },
    "design_check_6d": {
        "partial": 0.5,
        "today": {"rel_err": {"emit_z": -0.038, "emit_6d": 0.276}, "n_images": 20},
        "with_added": {"rel_err": {"emit_z": -0.016, "emit_6d": 0.109}, "n_images": 26},
    },
    "hgp_vs_gp": {
        "ratios": {
            "hgp_noise_over_true": 0.97,
            "gp_noise_over_true": 9.1,
            "sigma_hgp_over_gp": 0.13,
        },
        "gp": {"heldout_rmse": 0.1},
        "hgp": {"heldout_rmse": 0.0046},
    },
    "hysteresis_alarms": {
        "preisach_good": {"a": _case(0.05), "b": _case(0.44)},
        "preisach_bad": {"a": _case(1.0), "b": _case(1.33)},
        "preisach_false_alarms": 0,
        "preisach_missed": 0,
        "hgp_good": {
            "a": {"noise_ratio": 0.04, "heldout_ratio": 0.01},
            "b": {"noise_ratio": 0.05, "heldout_ratio": 0.12},
        },
        "hgp_bad": {
            "a": {"noise_ratio": 10.0, "heldout_ratio": 1.2},
            "b": {"noise_ratio": 12.0, "heldout_ratio": 11.0},
        },
        "hgp_false_alarms": 0,
        "hgp_missed": 0,
    },
    "preisach": {
        "anchor": {
            "T1000_N20000_forward_backward_s": 3.05,
            "T1000_N20000_peak_memory_mb": 1600.0,
            "T100_N1000_forward_backward_s": 0.042,
        },
        "checks": {
            "float32_threads1": {
                "T1000_N20100_forward_backward_s": 0.018,
                "T100_N990_forward_backward_s": 0.0007,
            },
            "float64_threads2": {
                "T1000_N20100_forward_backward_s": 0.010,
                "T100_N990_forward_backward_s": 0.0007,
            },
        },
        "records": [
            {"T": 1000, "N": 20100, "peak_memory_mb": 65.0},
            {"T": 100, "N": 990, "peak_memory_mb": 3.0},
        ],
    },
    "preisach_acceptance": {
        "targets": {"ratio_to_line": 0.5, "inside_2std": 0.8},
        "mean_inside_2std": 0.97,
        "records": [
            {"case": "slac", "ratio_to_line": 0.32, "fit_seconds": 1.4},
            {"case": "bipolar-0", "ratio_to_line": 0.20, "fit_seconds": 5.9},
            {"case": "bipolar-1", "ratio_to_line": 0.45, "fit_seconds": 2.0},
            {"case": "bh-0", "ratio_to_line": 0.05, "fit_seconds": 3.0},
            {"case": "bh-1", "ratio_to_line": 0.12, "fit_seconds": 3.0},
        ],
    },
    "preisach_slac": {
        "validation_selected": {"test_rms_pct": 0.060, "fit_seconds": 1.3},
        "straight_line_test_rms_pct": 0.197,
        "anchor_test_rms_pct": {"adam_10000_steps": 4.26},
        "train_rows": 62,
        "test_rows": 125,
    },
    "preisach_stream": {
        "rows": 1_000_000,
        "n_hysterons": 990,
        "targets": {"wall_s": 5.8, "peak_rss_mb": 500.0},
        "anchor": {"wall_s": 58.0, "peak_rss_mb": 8500.0},
        "cli_wall_s": 4.01,
        "cli_peak_rss_mb": 113.0,
        "speedup_vs_anchor": 14.5,
    },
    "reconstruction_6d": {
        "limits": {
            "rms_x": 0.05,
            "emit_x": 0.05,
            "emit_y": 0.05,
            "emit_z": 0.10,
            "emit_6d": 0.15,
            "wall_s": 120.0,
        },
        "diffaccel": {
            "errors": {
                "rms_x": 0.0028,
                "rms_pz": -0.001,
                "emit_x": -0.0029,
                "emit_y": -0.0007,
                "emit_z": -0.0102,
                "emit_6d": -0.0140,
            },
            "held_out_relative_l1": {"dipole_off": 0.070, "dipole_on": 0.078},
            "wall_s": 22.7,
            "cpu_s": 43.0,
        },
    },
    "reconstruction_6d_beams": _beams6d(),
    "reconstruction_distributed": {
        "single": {"held_out_relative_l1": 0.079, "training_s": 3.5},
        "torchrun_2_gloo": {"held_out_relative_l1": 0.078, "training_s": 6.0},
        "rms_relative_difference": [0.0021, -0.001, 0.0, 0.0005],
        "acceptance_max_abs_rms_difference": 0.02,
        "particles": 6144,
    },
    "reconstruction_step": {
        "acceptance": {
            "max_aten_ops": 300,
            "max_moment_term_aten_ops": 80,
            "max_host_syncs": 1,
        },
        "aten_ops_per_step": 375.4,
        "aten_ops_per_step_without_moment_term": 299.4,
        "host_syncs_per_step": 0.0,
        "device": "cpu",
        "threads": 1,
        "step_time_s": 0.0085,
    },
    "tracking": {
        "acceptance": {"min_ratio_kde": 100.0, "min_ratio_cic": 5.0},
        "ratio_vs_cheetah_kde": 156.2,
        "ratio_vs_cheetah_cic": 7.2,
        "ratio_vs_cheetah_cic_exact": 15.2,
        "n_particles": 100_000,
        "n_settings": 20,
        "timings": {"ours_linear_kde_forward_backward": {"median_s": 0.255}},
    },
    "xopt_hysteresis": {
        "hysteresis": {"median_final_best": 0.056, "time_s": 710.0},
        "xopt_ucb": {"median_final_best": 0.137, "time_s": 190.0},
        "ratio_xopt_ucb_over_hysteresis": 2.46,
        "seeds": 10,
        "steps": 50,
    },
}

#: stored figures no single run of the benchmark gives (the stored value was
#: assembled from other runs or annotated by hand)
NOT_FROM_ONE_RUN = {
    "resolution": {
        "default comparison (no smoothing), 64 / 320 pixels, 6144 particles"
    },
}


def _check_headline(name: str, result: dict) -> None:
    module = _module(BENCH / f"{name}.py")
    figures = module.headline(result)
    assert figures and all(isinstance(k, str) for k in figures)
    assert all(isinstance(v, str | int | float) for v in figures.values())
    stored = _stored(name)["headline"]
    expected = {
        k: v for k, v in stored.items() if k not in NOT_FROM_ONE_RUN.get(name, set())
    }
    assert {k: figures.get(k) for k in expected} == expected


@pytest.mark.parametrize("name", sorted(FAKES))
def test_headline_of_a_small_result_gives_the_stored_figures(name: str) -> None:
    _check_headline(name, FAKES[name])


@pytest.mark.parametrize(
    "name", sorted(p.stem for p in _scripts() if "result" in _stored(p.stem))
)
def test_headline_of_the_stored_full_result_gives_its_figures(name: str) -> None:
    _check_headline(name, _stored(name)["result"])


def test_a_headline_is_a_stored_result(meta, tmp_path) -> None:
    module = _module(BENCH / "reconstruction_6d_beams.py")
    path = meta.store(
        {**FAKES["reconstruction_6d_beams"], "name": "reconstruction_6d_beams"},
        module.headline,
        note=module.note,
        results=tmp_path,
    )
    stored = json.loads(path.read_text())
    assert stored["headline"]["held-out relative L1, worst"] == "0.115"
    assert stored["note"] == "outside a limit: nonlinear_ypy (rms_pz, emit_6d)"


def test_gpu_checks_summarise_the_files_of_a_run(tmp_path) -> None:
    module = _module(BENCH / "gpu_checks.py")

    def write(name: str, d: dict) -> None:
        (tmp_path / name).write_text("log line\n" + json.dumps(d) + "\n")

    for n, t in ((6144, 6e-4), (100000, 1.5e-3)):
        write(f"step_{n}.json", {"step_time_s": t, "cuda_graph": True})
        write(f"step_{n}_eager.json", {"step_time_s": 4.5e-3, "cuda_graph": False})
    write("process.json", {"ratio": 5.5})
    write("sixd.json", {"diffaccel": {"wall_s": 40.2, "fails": ["emit_z"]}})
    result = module.summarise(tmp_path)
    assert result["missing"] == ["tracking"]
    assert result["steps"]["100000"]["eager_step_time_s"] == [4.5e-3]
    figures = module.headline(result)
    key = "default 4D step, CUDA graph, 6 144 / 100 000 particles (limits 3 / 5 ms)"
    assert figures[key] == "0.60 ms / 1.50 ms"
    assert figures["shared 6D benchmark on the GPU"] == "40 s, fails: emit_z"
