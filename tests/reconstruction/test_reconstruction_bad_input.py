"""Bad arguments to the reconstruction API: one-line ValueErrors naming them."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from diffaccel.reconstruction import (
    ReconstructionConfig,
    fit_gaussian,
    image_errors,
    moment_errors,
    reconstruct,
    training_selection,
)
from diffaccel.reconstruction.pipeline import as_scans


@pytest.fixture(scope="module")
def small_result(small_scan):
    config = ReconstructionConfig(n_particles=256, steps=2, snapshots=1)
    return reconstruct(small_scan, config, uncertainty=False)


@pytest.mark.parametrize(
    ("given", "match"),
    [
        ({"scan": "12"}, "got the text '12'"),  # was read as [1, 2]
        ([1.5], "1.5 is not an integer index"),  # was [1]
        ([True, False], "True is not an integer index"),  # was [1, 0]
        ([float("nan")], "nan is not an integer index"),
        (5, "expected a list of integer indices; got 5"),
    ],
)
def test_training_selection_refuses_what_is_not_an_index(
    small_scan, given, match
) -> None:
    with pytest.raises(ValueError, match=match):
        training_selection(as_scans(small_scan), given)


def test_training_selection_takes_numpy_and_tensor_integers(small_scan) -> None:
    sel = training_selection(as_scans(small_scan), [np.int64(1), torch.tensor(3)])
    assert dict(sel) == {"scan": [1, 3]}


def test_image_errors_refuse_images_a_relative_error_cannot_use() -> None:
    p, m = torch.rand(3, 4, 4), torch.rand(3, 4, 4)
    # each of these returned a number (nan, 6.9e300, ...) without complaint
    with pytest.raises(ValueError, match="measured images contain NaN"):
        image_errors(p, m * float("nan"))
    with pytest.raises(ValueError, match="measured image 0 sums to <= 0"):
        image_errors(p, torch.zeros_like(m))
    with pytest.raises(ValueError, match="no images to compare"):
        image_errors(p[:0], m[:0])
    # numpy arrays are images too
    assert image_errors(p.numpy(), p.numpy())["relative_l1"] == 0.0
    x = np.random.default_rng(0).normal(size=(100, 6))
    assert moment_errors(x, x)["emit_x"] == 0.0


def test_sample_and_predict_refuse_bad_counts_and_maps(small_result) -> None:
    for n in (0, 1.5, float("nan"), True, 10**12):
        with pytest.raises(ValueError, match="n must be an integer"):
            small_result.sample(n)
    settings = small_result.forward.check_settings(torch.tensor([[1.0], [2.0]]))
    with pytest.raises(ValueError, match="draw_particles must be an integer"):
        small_result.predict_images(settings, return_std=True, draw_particles=1)
    with pytest.raises(ValueError, match="forward must be a ScreenForwardModel"):
        small_result.predict_images(settings, forward="x")
    # maps of other settings gave images of those settings, silently
    other = small_result.forward.transfer_maps(torch.tensor([[5.0], [6.0], [7.0]]))
    with pytest.raises(ValueError, match=r"maps \(3, 7, 7\) must be"):
        small_result.predict_images(settings, maps=other)


def test_fit_gaussian_names_bad_images_before_the_least_squares(
    awa6d_two_settings,
) -> None:
    forwards, images, settings = awa6d_two_settings
    # NaN images reached LAPACK: an MKL error on stderr and a torch assert
    with pytest.raises(ValueError, match="images must be finite"):
        fit_gaussian(forwards, [i * float("nan") for i in images], settings)
    with pytest.raises(ValueError, match="one image per setting"):
        fit_gaussian(forwards, [i[:2] for i in images], settings)
    with pytest.raises(ValueError, match="one forward model, image stack"):
        fit_gaussian(forwards[:1] * 3, images, settings)


def test_training_selection_refuses_one_quadrupole_value(small_awa6d) -> None:
    # --train-indices 0,1 --dims 6 on the shared 6D file (one k1, TDC off and
    # on) must be refused naming the scan, not fail in tracking with "NaN or
    # infinite positions"
    scan = small_awa6d[small_awa6d.names[0]]
    k1 = scan.settings[:, scan.setting_names.index("SCAN_QUAD.k1")]
    same = torch.nonzero(k1 == k1[0])[:, 0].tolist()
    assert len(same) == 2  # TDC off and on
    with pytest.raises(
        ValueError, match=r"single value of the scanned quadrupole"
    ) as e:
        training_selection(small_awa6d, same)
    for name in small_awa6d.names:
        assert f"scan {name!r}: SCAN_QUAD.k1 = {float(k1[0]):g}" in str(e.value)
    with pytest.raises(ValueError, match=r"single value of the scanned quadrupole"):
        reconstruct(small_awa6d, ReconstructionConfig(dims=6), train_indices=same)


def test_training_selection_takes_one_quadrupole_value_next_to_a_scan(
    small_awa6d,
) -> None:
    # a scan at one setting is fine while another scan varies the quadrupole
    first, second = small_awa6d.names
    sel = training_selection(small_awa6d, {first: [0], second: [0, 2, 4]})
    assert dict(sel) == {first: [0], second: [0, 2, 4]}
