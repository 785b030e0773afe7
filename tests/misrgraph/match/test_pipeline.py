"""Matching pipeline bookkeeping that needs no imagery."""

from __future__ import annotations

import numpy as np

from misrgraph.match.pipeline import AN, MatchConfig, MatchedObservations, TieFeature, _drop_inconsistent
from misrgraph.match.precision import PrecisionFit


def test_inconsistent_conjugates_are_dropped_and_features_renumbered():
    """Feature 0 loses one of four conjugates (kept); feature 1 loses one of two and falls below
    3 cameras (dropped whole); feature 2 is untouched and becomes feature 1."""
    out = MatchedObservations(candidates=9)
    rows = []
    for f, cams in enumerate(([0, 1, 2, 3], [0, 1], [5, 6, 7])):
        out.add(f, AN, 100.0 * f, 50.0, 0.05)
        for c in cams:
            out.add(f, c, 100.0 * f + c, 50.0 + c, 0.1)
            rows.append(len(out) - 1)
    out.pending_rows = np.array(rows)
    bad = np.zeros(len(rows), bool)
    bad[[1, 4]] = True  # feature 0 camera 1; feature 1 camera 0
    out.precision = PrecisionFit(outlier=bad)
    feats = [TieFeature(10 + f, 100.0 * f, 50.0) for f in range(3)]
    kept_f, kept = _drop_inconsistent(feats, out, MatchConfig(min_cameras=3))
    assert [f.window_row for f in kept_f] == [10, 12]
    assert kept.reasons["inconsistent with the pass (redundancy check)"] == 2
    assert kept.reasons["seen in fewer than 3 cameras"] == 1
    pairs = sorted(zip(kept.feature, kept.camera))
    assert pairs == sorted([(0, AN), (0, 0), (0, 2), (0, 3), (1, AN), (1, 5), (1, 6), (1, 7)])
    # positions travel with their observations
    i = [k for k, (f, c) in enumerate(zip(kept.feature, kept.camera)) if (f, c) == (1, 6)][0]
    assert kept.line[i] == 206.0 and kept.sample[i] == 56.0
