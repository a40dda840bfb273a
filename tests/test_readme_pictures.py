"""The README's pictures of the browser viewer are made by ``docs/viewer_pictures.py`` (headless
Chromium), never by hand: this test runs the script and fails while a committed picture's panel
(labels, units, slider ranges, the gallery's query controls) differs from the one made now, naming
the command that brings it up to date; the README shows each picture."""
from __future__ import annotations

import importlib.util
import os

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCRIPT = os.path.join(ROOT, "docs", "viewer_pictures.py")
DIFFERENT = 0.04
"""Largest share of the panel's pixels that may differ (the readout's milliseconds change)."""


def _script():
    spec = importlib.util.spec_from_file_location("viewer_pictures", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_readme_shows_the_pictures_the_script_makes_now(tmp_path):
    from PIL import Image

    pictures = _script()
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        readme = f.read()
    made = pictures.make(str(tmp_path))
    x0, y0, x1, y1 = pictures.PANEL
    for path in made:
        name = os.path.basename(path)
        assert f"(docs/{name})" in readme, f"the README does not show docs/{name}"
        new = np.asarray(Image.open(path).convert("RGB"), np.int16)
        assert new.shape == (pictures.SIZE[1], pictures.SIZE[0], 3) and new[:, :x0].std() > 10  # drawn, not blank
        old = np.asarray(Image.open(os.path.join(ROOT, "docs", name)).convert("RGB"), np.int16)
        assert old.shape == new.shape, f"docs/{name} is out of date: run python docs/viewer_pictures.py"
        differs = (np.abs(new[y0:y1, x0:x1] - old[y0:y1, x0:x1]).sum(axis=2) > 60).mean()
        assert differs < DIFFERENT, (f"docs/{name}'s panel differs from the viewer's now ({100 * differs:.1f} % of "
                                     f"its pixels): run python docs/viewer_pictures.py")
