"""The run report shows the tension spectra of every point (issue 13): small multiples, one panel
per point, label and spectrum flags in each panel's title, the rig's modes as vertical lines, at
most 24 panels a figure; cheap enough for a 180-point run.

The panel count is checked twice: the count the builder reports, and the panel frames counted in
the written PNG (connected grey rectangles, scipy.ndimage), which the builder does not compute."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage
from scipy.signal import welch

from cdpr.pipelines.report import SPECTRA_PER_FIGURE, decimate_spectrum, spectra_grid_figures


def _spectra(n: int, fs: float = 200.0, m: int = 8, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(1200) / fs
    freqs, psd = [], []
    for i in range(n):
        x = rng.normal(0, 0.05, (t.size, m)) + 0.3 * np.sin(2 * np.pi * (5 + i % 30) * t)[:, None]
        f, p = welch(x, fs=fs, nperseg=256, axis=0)
        freqs.append(f)
        psd.append(p.T)
    modes = np.tile([9.5, 14.0, 22.0, 30.0, 41.0, 55.0], (n, 1))
    return freqs, psd, modes


def _frames_in_png(path: Path) -> int:
    """Panels in the PNG: connected grey outlines (the frames) of at least 150 pixels."""
    import matplotlib.image as mpimg

    img = (mpimg.imread(path)[..., :3] * 255).astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    grey = (abs(r - g) < 6) & (abs(g - b) < 6) & (r > 120) & (r < 240)  # grey frames, antialiased
    lab, n = ndimage.label(grey, structure=np.ones((3, 3)))
    sizes = ndimage.sum(grey, lab, index=np.arange(1, n + 1))
    return int((sizes >= 150).sum())


def test_one_panel_per_point_split_at_24(tmp_path: Path) -> None:
    n = 30
    freqs, psd, modes = _spectra(n)
    freqs[3], psd[3] = np.zeros(0), np.zeros((8, 0))  # a point without a spectrum keeps its panel
    flags = ["" for _ in range(n)]
    flags[1] = "too_few_periods"
    flags[2] = "masked;spectrum_peak_near_mode"
    labels = [f"pt{i}" for i in range(n)]
    grid = spectra_grid_figures(
        tmp_path, labels, flags, freqs, psd, modes, [f"c{j}" for j in range(8)]
    )
    assert grid.panels == [24, 6]
    assert [f.name for f in grid.figures] == ["spectra_1.png", "spectra_2.png"]
    assert [_frames_in_png(tmp_path / f.name) for f in grid.figures] == [24, 6]
    assert "points 1–24 of 30" in grid.figures[0].title


def test_few_points_one_figure(tmp_path: Path) -> None:
    freqs, psd, modes = _spectra(5)
    grid = spectra_grid_figures(tmp_path, list("abcde"), [""] * 5, freqs, psd, modes)
    assert grid.panels == [5] and grid.figures[0].name == "spectra.png"
    assert _frames_in_png(tmp_path / "spectra.png") == 5


def test_decimation_keeps_power_and_the_peak() -> None:
    f = np.linspace(0.0, 100.0, 257)
    P = np.full((2, 257), 1e-4)
    P[:, 100] = 1.0  # a peak at 38.9 Hz
    fd, Pd = decimate_spectrum(f, P, max_bins=64)
    assert fd.size <= 64 and Pd.shape == (2, fd.size)
    k = int(np.argmax(Pd[0]))
    assert abs(fd[k] - f[100]) <= 4 * (f[1] - f[0])  # the peak stays in its block
    # the mean PSD is the power over the band divided by the band: preserved by block means
    blocks = int(np.ceil(256 / 64))
    assert Pd[0, k] == pytest.approx((1.0 + (blocks - 1) * 1e-4) / blocks)


def test_180_points_in_a_few_seconds(tmp_path: Path) -> None:
    freqs, psd, modes = _spectra(180)
    flags = ["too_few_periods" if i % 7 == 0 else "" for i in range(180)]
    # CPU time of this process: what the figures cost, whatever else the machine runs (wall time
    # under a load of 8 on two cores was 8.6 s for 1.5 s of work)
    t0 = time.process_time()
    grid = spectra_grid_figures(tmp_path, [f"p{i}" for i in range(180)], flags, freqs, psd, modes)
    took = time.process_time() - t0
    assert sum(grid.panels) == 180 and len(grid.figures) == int(np.ceil(180 / SPECTRA_PER_FIGURE))
    print(f"180 points: {took:.2f} s of CPU")
    assert took < 6.0  # about 1.5 s on an idle core
