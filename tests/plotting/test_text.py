"""User names with TeX special characters are drawn literally (no crash at savefig)."""

from __future__ import annotations

import io

import matplotlib as mpl
import pytest
import torch

from diffaccel.plotting import plot_image_comparison
from diffaccel.plotting.text import literal

NAMES = ["Q$1.k1", r"$\frac{a$", "I_max^2 [%] & #", r"\alpha $x$"]


@pytest.mark.parametrize("name", NAMES, ids=["dollar", "bad-math", "specials", "tex"])
def test_image_comparison_with_a_tex_name_draws(name: str) -> None:
    g = torch.Generator().manual_seed(0)
    meas = torch.rand(2, 8, 8, generator=g)
    fig = plot_image_comparison(
        meas, meas.flip(-1), torch.tensor([[1.0], [2.0]]), setting_name=name, title=name
    )
    fig.savefig(io.BytesIO(), format="png")
    assert name in fig.texts[-1].get_text().replace(r"\$", "$")


def test_usetex_in_the_users_rc_is_ignored() -> None:
    meas = torch.rand(1, 4, 4, generator=torch.Generator().manual_seed(1))
    with mpl.rc_context({"text.usetex": True}):
        fig = plot_image_comparison(meas, meas, torch.tensor([[0.0]]), title="a_b%")
    assert not any(t.get_usetex() for t in fig.texts)


def test_literal_escapes_only_dollars() -> None:
    assert literal(r"a$b_c\d") == r"a\$b_c\d"


def test_preisach_fit_with_tex_column_names_draws() -> None:
    from diffaccel.hysteresis.synthetic import synthetic_magnet, synthetic_measurement
    from diffaccel.plotting.hysteresis import plot_preisach_fit

    current, field, _ = synthetic_measurement(noise=0.0)
    fig = plot_preisach_fit(
        synthetic_magnet(),
        current,
        field,
        n_train=21,
        input_label=NAMES[1],
        output_label=NAMES[0],
    )
    fig.savefig(io.BytesIO(), format="png")
