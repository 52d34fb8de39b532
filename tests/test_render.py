"""`dem render` as a user runs it: the PNG read back pixel by pixel (issue 49, part 4: the colour
bar sat over the particles and its first number was hidden).

What the picture must show, and how it is read: on the white background every drawn pixel is
either a particle or the colour bar with its title and numbers. The columns that hold any drawn
pixel form two groups, the particles on the left and the bar on the right, with a band of empty
columns between them (nothing overlaps). The bar is the band of columns whose pixels are coloured
(saturated: max - min channel > 60) over at least 30 % of the height; the numbers are the dark
pixels (every channel < 110) right of it, one group of rows per number: the five labels of the
bar, the lowest and the highest included. Nothing touches the image's border (no number is cut)."""
import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _runs(mask, join=6):
    """Index ranges [a, b] where ``mask`` is true, runs closer than ``join`` merged."""
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    out = [[idx[0], idx[0]]]
    for i in idx[1:]:
        if i - out[-1][1] <= join:
            out[-1][1] = i
        else:
            out.append([i, i])
    return out


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """The packed-bed example after its first output (2,000 particles, a heated floor: a range of
    temperatures for the bar)."""
    out = tmp_path_factory.mktemp("render") / "out"
    p = subprocess.run([sys.executable, "-m", "dem.cli", "run", os.path.join("examples", "packed_bed_heating.toml"),
                        "--end-time", "60", "--out", str(out), "--quiet"], cwd=ROOT, capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    return out


@pytest.mark.parametrize("color", ["temperature", "heat_rate"])
def test_colour_bar_beside_the_particles_with_every_number(run_dir, tmp_path, color):
    from PIL import Image
    png = tmp_path / f"{color}.png"
    p = subprocess.run([sys.executable, "-m", "dem.cli", "render", str(run_dir), "--png", str(png),
                        "--color", color], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stdout[-2000:] + p.stderr[-3000:]
    img = np.asarray(Image.open(png).convert("RGB")).astype(int)
    H, W, _ = img.shape
    drawn = (img < 245).any(axis=2)
    # nothing cut at the border
    assert not drawn[:2].any() and not drawn[-2:].any() and not drawn[:, :2].any() and not drawn[:, -2:].any()
    groups = _runs(drawn.any(axis=0))
    assert len(groups) == 2, groups
    (p0, p1), (b0, b1) = groups
    assert b0 - p1 >= 0.03 * W, groups            # an empty band between the particles and the bar
    assert p1 - p0 > 2 * (b1 - b0), groups         # the particles take most of the picture
    coloured = (img.max(axis=2) - img.min(axis=2)) > 60
    bar_cols = np.flatnonzero(coloured[:, b0:b1 + 1].sum(axis=0) > 0.3 * H) + b0
    assert bar_cols.size >= 5, "no colour bar found"
    rows = np.flatnonzero(coloured[:, bar_cols[bar_cols.size // 2]])
    r0, r1 = rows[0], rows[-1]
    assert r1 - r0 > 0.3 * H
    # the bar's colours run from the colour map's one end to the other: top and bottom differ
    top, bottom = img[r0 + 2, bar_cols[bar_cols.size // 2]], img[r1 - 2, bar_cols[bar_cols.size // 2]]
    assert np.abs(top - bottom).max() > 100, (top, bottom)
    dark = img.max(axis=2) < 110
    labels = _runs(dark[r0 - 8:r1 + 9, bar_cols[-1] + 1:b1 + 1].any(axis=1), join=1)
    assert len(labels) == 5, labels                # every number of the bar, the first included
    assert labels[0][0] <= 10 and labels[-1][1] >= (r1 - r0) + 6, labels   # at the bar's two ends
