"""The small pass adjusted, and its Projection Parameters over one block: shared by the PP and
terrain tests."""

from __future__ import annotations

import numpy as np
import pytest

#: The middle of the small pass's features (path 37, 55 N going south for 15 minutes).
PP_BLOCK = 57


@pytest.fixture(scope="session")
def adjusted(small_pass, small_pass_dir):
    from misrgraph.estimate.adjust import adjust_pass
    from misrgraph.io.camera import load_camera_model

    sc, op = small_pass
    cam = load_camera_model(small_pass_dir / "camera_model.h5").at_temperature(op.temperature_c)
    res = adjust_pass(op, cam, sc.dem, sc.gcps)
    return sc, op, cam, res


@pytest.fixture(scope="session")
def pp(adjusted):
    from misrgraph.products.pp import compute_pp

    _, op, _, res = adjusted
    return compute_pp(op, res, op.path, np.array([PP_BLOCK]))
