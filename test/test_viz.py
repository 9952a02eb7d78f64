"""Figures are written where asked: a PNG in 256 colours (the committed results must stay
small), another format as matplotlib writes it; the heatmap lands in a folder it creates."""

from __future__ import annotations

import numpy as np
from PIL import Image

from w2e_ros.core.model.viz import heatmap_figure, write_figure


def _figure():
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot(np.linspace(0, 1, 50), np.sin(np.linspace(0, 6, 50)))
    return fig


def test_png_is_written_in_256_colours_and_the_figure_closed(tmp_path):
    import matplotlib.pyplot as plt

    fig = _figure()
    out = write_figure(fig, tmp_path / "a" / "curve.png", dpi=80)
    with Image.open(out) as im:
        assert im.format == "PNG" and im.mode == "P" and len(im.getcolors()) <= 256
    assert not plt.fignum_exists(fig.number)


def test_other_formats_are_written_as_they_are(tmp_path):
    out = write_figure(_figure(), tmp_path / "curve.pdf", dpi=80)
    assert out.read_bytes().startswith(b"%PDF")


def test_heatmap_creates_its_folder(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(-0.3, 0.3, (500, 3))
    out = heatmap_figure(pts, {"affordance": rng.random(500)}, tmp_path / "x" / "y" / "h.png")
    with Image.open(out) as im:
        assert im.mode == "P" and im.size[0] > 100
