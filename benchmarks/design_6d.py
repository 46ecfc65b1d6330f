"""Observability and recommended settings of a 6D scan file (no training).

On the AWA 6D layout of ``DATA`` (default: the shared 6D training file):

- the relative singular values of the moment design
  (``reconstruction.design``) over all 21 covariance entries and over the
  longitudinal block (entries with z or pz, the transverse ones held), for the
  file's scans and for the same scans plus: the cavity at -4 MV on every scan
  (``tdc_minus``), the dipole scan at 0.8 of its angle (``dipole_0.8``), and
  both;
- the unseen directions in words and the quantities left to the prior;
- the recommendation for ``--knob`` ranges (default the cavity voltage
  -4 ... 4 MV and the dipole angle -0.40 ... -0.28 rad) and the singular values
  with the recommended settings added;
- the wall time of the design (observability and recommendation, from the
  image-moment beam), the quantity the issue limits to 5 s.

The beam is the file's truth for the table (``--beam truth``) or the Gaussian
fit of the image moments (``--beam images``, what ``diffaccel design`` uses
without a result folder). The last line is JSON.

Usage: ``python benchmarks/design_6d.py [DATA] [--beam truth|images]``
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch
from _meta import add_store_flag, emit, git_commit
from _sixd import DATA

from diffaccel.data.scans import read_scans
from diffaccel.reconstruction import ScreenForwardModel
from diffaccel.reconstruction import design as dz

SHARED = str(DATA / "sixd_synthetic_train.h5")


def _smallest(values: list[float], n: int = 2) -> list[float]:
    return sorted(values)[:n][::-1]


def _sci(values: list[float]) -> str:
    """``4.2e-3, 6.9e-5``: two significant digits, short exponents."""
    out = []
    for v in values:
        mantissa, exponent = f"{v:.1e}".split("e")
        out.append(f"{mantissa}e{int(exponent)}")
    return ", ".join(out)


def headline(result: dict) -> dict[str, str]:
    """The docs page's figures: the two smallest longitudinal singular values."""
    table = result["table"]
    data = Path(result["data"])
    where = "shared 6D scan" if data.name == Path(SHARED).name else data.name
    n_images = sum(len(r["values"]) for r in result["recommended"])
    return {
        f"two smallest singular values, {where}": _sci(
            table["today"]["longitudinal_two_smallest"]
        ),
        "with the cavity at -4 MV and the dipole at 0.8 of its angle": _sci(
            table["both"]["longitudinal_two_smallest"]
        ),
        f"the {n_images} recommended images": _sci(
            result["with_recommended"]["longitudinal_two_smallest"]
        ),
        "design time": f"{result['design_s']:.2f} s",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", nargs="?", default=SHARED)
    ap.add_argument("--beam", choices=("truth", "images"), default="truth")
    ap.add_argument(
        "--knob",
        action="append",
        default=None,
        help="ELEMENT.param=LOW:HIGH[:N] (repeatable)",
    )
    add_store_flag(ap)
    args = ap.parse_args()
    knobs = args.knob or ["SCAN_TDC.voltage=-4e6:4e6", "SCAN_DIPOLE.angle=-0.40:-0.28"]
    ds = read_scans(args.data)
    layouts = dz.layouts_from_dataset(ds)
    t0 = time.perf_counter()
    cov_images = dz.beam_from_images(ds)
    t_fit = time.perf_counter() - t0
    if args.beam == "truth" and ds.ground_truth is not None:
        cov = torch.cov(ds.ground_truth.to(torch.float64).T)
    else:
        cov = cov_images
    maps = {x.name: x.maps() for x in layouts}

    def tdc_minus(name: str) -> torch.Tensor:
        x = next(y for y in layouts if y.name == name)
        col = x.forward.names.index("SCAN_TDC.voltage")
        s = x.settings[x.settings[:, col] > 0].clone()
        s[:, col] = -s[:, col]
        return x.forward.transfer_maps(s)

    def dipole(frac: float) -> torch.Tensor:
        x = next(
            y for y in layouts if "SCAN_DIPOLE" in y.forward.beamline.element_names
        )
        angle = dz._current_value(x.forward, "SCAN_DIPOLE.angle")
        fwd = ScreenForwardModel(
            x.forward.beamline, [*x.forward.names, "SCAN_DIPOLE.angle"], x.forward.p0c
        )
        s = torch.cat(
            [x.settings, torch.full((x.settings.shape[0], 1), frac * angle)], 1
        )
        return fwd.transfer_maps(s.to(torch.float64))

    base = list(maps.values())
    minus = [tdc_minus(n) for n in maps]
    table = {
        "today": base,
        "tdc_minus": base + minus,
        "dipole_0.8": [*base, dipole(0.8)],
        "both": base + minus + [dipole(0.8)],
    }
    rows = {}
    for name, m in table.items():
        obs = dz.observability(m, cov, partials=())
        rows[name] = {
            "longitudinal_two_smallest": _smallest(obs.longitudinal_singular_values),
            "all_three_smallest": _smallest(obs.singular_values, 3),
            "unseen": [u["words"] for u in obs.unseen],
        }
        print(
            f"{name:>10}: longitudinal two smallest "
            + ", ".join(f"{v:.2g}" for v in rows[name]["longitudinal_two_smallest"])
            + "; all entries three smallest "
            + ", ".join(f"{v:.2g}" for v in rows[name]["all_three_smallest"])
        )
    t0 = time.perf_counter()
    obs = dz.observability(layouts, cov_images)
    rec = dz.recommend(layouts, cov_images, [dz.parse_knob(k) for k in knobs])
    t_design = time.perf_counter() - t0
    print(obs.summary_line())
    for r in rec["recommended"]:
        print(
            f"  {r['scan']}: {r['n_images']} images {r['names']} = {r['values']}; "
            + ", ".join(f"{k} {100 * v:.1f} %" for k, v in r["expected_std"].items())
        )
    sv, lsv = dz.singular_values_with(layouts, cov, rec["recommended"])
    print(
        "with the recommended settings: longitudinal two smallest "
        + ", ".join(f"{v:.2g}" for v in _smallest(lsv))
        + f"; design {t_design:.2f} s (+ image-moment fit {t_fit:.2f} s)"
    )
    emit(
        {
            "name": "design_6d",
            "commit": git_commit(),
            "data": args.data,
            "beam": args.beam,
            "table": rows,
            "observability": {
                "unseen": [u["words"] for u in obs.unseen],
                "left_to_prior": obs.left_to_prior(),
                "singular_values": obs.singular_values,
            },
            "recommended": [
                {k: r[k] for k in ("scan", "names", "values", "expected_std")}
                for r in rec["recommended"]
            ],
            "baseline_std": {t: rec["baseline_std"][t] for t in rec["targets"]},
            "with_recommended": {
                "longitudinal_two_smallest": _smallest(lsv),
                "all_three_smallest": _smallest(sv, 3),
            },
            "design_s": t_design,
            "image_fit_s": t_fit,
        },
        headline=headline,
        store_result=args.store,
    )


if __name__ == "__main__":
    main()
