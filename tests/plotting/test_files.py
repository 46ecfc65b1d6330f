"""Figures written as PNG files."""

from __future__ import annotations

from pathlib import Path

from matplotlib.figure import Figure

from diffaccel.plotting.files import save_figures, save_png

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _figure(width_in: float) -> Figure:
    fig = Figure(figsize=(width_in, 1.0))
    fig.add_subplot().plot([0, 1], [1, 0])
    return fig


def test_save_png_writes_a_png_of_the_asked_resolution(tmp_path: Path) -> None:
    from PIL import Image

    path = save_png(_figure(2.0), tmp_path / "a.png", dpi=50)
    assert path == tmp_path / "a.png"
    assert path.read_bytes()[:8] == PNG_MAGIC
    with Image.open(path) as im:
        assert im.size == (100, 50)  # 2 x 1 inches at 50 dpi
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.png"]  # no temp file


def test_save_figures_writes_each_before_drawing_the_next(tmp_path: Path) -> None:
    seen = []

    def figures():
        for name in ("one.png", "two.png"):
            seen.append(sorted(p.name for p in tmp_path.iterdir()))
            yield name, _figure(1.0)

    assert save_figures(figures(), tmp_path, dpi=20) == ["one.png", "two.png"]
    assert seen == [[], ["one.png"]]
