"""Soft-iron B-H loops, bipolar quadrupoles and the SLAC quadrupole with ``fit_magnet``.

Cases (fit the first rows, predict the rest, CLI defaults):

* ``iron-<shape>``: synthetic soft-iron major loops
  (``hysteresis.synthetic.soft_iron_loop``, not made by a Preisach model),
  H in A/m up to 1e5 (five orders of magnitude), B in tesla; the training rows
  are the ascending branch from negative remanence, the test rows the
  descending branch to negative saturation and back to zero. Three shapes:
  ``tanh`` (coercive field 1e-3 of the range), ``atan`` (3e-3, wide switching,
  slow approach to saturation) and ``erf`` (1e-2, square loop);
* ``bipolar-<seed>``: ``hysteresis.synthetic.bipolar_quadrupole_case``;
* ``slac``: the SLAC LCLS-II quadrupole 4194, 62 -> 125 rows (if the shared
  data are present).

Each record gives the held-out rms in % of the training output range, the
ratio to a straight line fitted to the same rows, the share of held-out rows
inside 2 std, the fit time, the chosen mesh warp and any band fallback.
Prints one JSON object on the last line.
"""

from __future__ import annotations

import argparse
import platform
import time
import warnings
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit, span

from diffaccel.data import read_magnet_csv
from diffaccel.hysteresis import InputRangeWarning, fit_magnet
from diffaccel.hysteresis.synthetic import bipolar_quadrupole_case, soft_iron_loop

SLAC = (
    Path(__file__).resolve().parents[1]
    / "data"
    / "hysteresis"
    / "slac_lcls2_quad_4194"
    / "measurements.csv"
)
IRON = {
    "tanh": {"coercive": 1e-3, "width": 0.5, "js": 1.8},
    "atan": {"coercive": 3e-3, "width": 2.0, "js": 1.6},
    "erf": {"coercive": 1e-2, "width": 0.2, "js": 2.0},
}


def _rms(x: torch.Tensor) -> float:
    return float(x.pow(2).mean().sqrt())


def _line(current, field, n) -> float:
    basis = torch.stack([torch.ones_like(current), current], dim=1)
    coef = torch.linalg.lstsq(basis[:n], field[:n, None]).solution
    return _rms((basis @ coef).squeeze(1)[n:] - field[n:])


def cases(seeds: int, which: set[str]) -> list:
    out = []
    if "iron" in which:
        for shape, kw in IRON.items():
            h, b, n = soft_iron_loop(shape=shape, **kw)
            out.append((f"iron-{shape}", h, b, n))
    if "bipolar" in which:
        for seed in range(seeds):
            c, f, n, _ = bipolar_quadrupole_case(seed)
            out.append((f"bipolar-{seed}", c, f, n))
    if "slac" in which and SLAC.exists():
        hist = read_magnet_csv(SLAC)
        out.append(("slac", hist.input, hist.output, 62))
    return out


def evaluate(name, current, field, n) -> dict:
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        fit = fit_magnet(current[:n], field[:n])
        seconds = time.perf_counter() - t0
        with torch.no_grad():
            pred = fit.model(current)
            std = fit.band.std(fit.model, current)
    err = pred[n:] - field[n:]
    span = float(field[:n].max() - field[:n].min())
    test, line = _rms(err), _line(current, field, n)
    return {
        "case": name,
        "train_rows": n,
        "test_rows": len(current) - n,
        "symmetric": fit.symmetric,
        "input_range": list(fit.model.input_range),
        "mesh_adapt": fit.mesh_adapt,
        "mesh_validation": fit.mesh_validation,
        "test_rms_pct": 100 * test / span,
        "test_max_pct": 100 * float(err.abs().max()) / span,
        "line_test_rms_pct": 100 * line / span,
        "ratio_to_line": test / line,
        "inside_2std": float((err.abs() <= 2 * std[n:]).double().mean()),
        "band_calibration": fit.calibration,
        "band_fallback": fit.band_fallback,
        "fit_seconds": seconds,
    }


def _short_e(value: float) -> str:
    """``1e-3``: one significant digit, a short exponent."""
    mantissa, exponent = f"{value:.0e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: the soft-iron loops' held-out error, band, time."""
    iron = [r for r in result["records"] if r["case"].startswith("iron-")]
    if not iron:
        return {
            f"{r['case']}, held-out error": f"{r['test_rms_pct']:.2f} % of the range"
            for r in result["records"]
        }
    coercive = ", ".join(
        _short_e(IRON[r["case"].removeprefix("iron-")]["coercive"]) for r in iron
    )
    errors = ", ".join(f"{r['test_rms_pct']:.2f} %" for r in iron)
    line = span([r["line_test_rms_pct"] for r in iron], ".0f")
    inside = [f"{100 * r['inside_2std']:.0f} %" for r in iron]
    seconds = span([r["fit_seconds"] for r in iron], ".0f")
    return {
        f"soft-iron loops (coercive field {coercive} of the range), held-out error": (
            f"{errors} of the B range (straight line {line} %)"
        ),
        "inside 2 std": (
            f"{inside[0]} on each" if len(set(inside)) == 1 else ", ".join(inside)
        ),
        "fit time": f"{seconds} s each",
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3, help="bipolar magnets")
    parser.add_argument("--cases", default="iron,bipolar,slac")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON")
    add_store_flag(parser)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore", InputRangeWarning)
    c, f, n, _ = bipolar_quadrupole_case(0)  # pay one-off imports before timers
    fit_magnet(c[:n], f[:n], mesh_size=4, steps=2, mesh_adapt=0.0)
    records = []
    for case in cases(args.seeds, set(args.cases.split(","))):
        records.append(evaluate(*case))
        r = records[-1]
        print(
            f"{r['case']}: {r['test_rms_pct']:.3f} % (line {r['line_test_rms_pct']:.3f}"
            f" %, ratio {r['ratio_to_line']:.3f}), inside 2 std "
            f"{100 * r['inside_2std']:.0f} %, adapt {r['mesh_adapt']}, "
            f"{r['fit_seconds']:.1f} s",
            flush=True,
        )
    result = {
        "name": "preisach_bh_loops",
        "device": "cpu",
        "threads": torch.get_num_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "git_commit": git_commit(),
        "targets": {"ratio_to_line": 0.5, "inside_2std": 0.8, "fit_seconds": 20.0},
        "records": records,
    }
    emit(result, args.out, headline=headline, store_result=args.store)


if __name__ == "__main__":
    main()
