"""Middlebury templeSparseRing calibration (shared data)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from o3drbf.cameras.model import load_cameras

DATA = Path(__file__).resolve().parents[3] / "shared" / "data"
TEMPLE = DATA / "middlebury_templeSparseRing"

if not DATA.is_dir():
    pytest.skip(f"needs the shared data folder {DATA} (not present: a clone without ../shared)", allow_module_level=True)

pytestmark = pytest.mark.shared_data

# Bounding box from the data set's README.
LO = np.array([-0.073568, 0.021728, -0.012445])
HI = np.array([0.028855, 0.181892, 0.062736])


def test_temple_par_file():
    cams = load_cameras(TEMPLE / "templeSR_par.txt")
    assert cams.format == "middlebury" and len(cams) == 16
    assert cams.names[0] == "templeSR0001.png"
    assert all((c.width, c.height) == (640, 480) for c in cams)  # read from the PNG headers
    np.testing.assert_allclose(cams[0].K, [[1520.4, 0, 302.32], [0, 1525.9, 246.87], [0, 0, 1]])
    corners = np.array([[x, y, z] for x in (LO[0], HI[0]) for y in (LO[1], HI[1]) for z in (LO[2], HI[2])])
    for cam in cams:
        assert cam.in_image(corners).all(), cam.name
    dist = [np.linalg.norm(c.center - (LO + HI) / 2) for c in cams]
    assert 0.557 < min(dist) and max(dist) < 0.575  # SOURCES.md: 0.558-0.574 m
    # The folder is detected too.
    assert len(load_cameras(TEMPLE)) == 16
