"""Errors per layer of depth: against numpy on hand-made points."""

import numpy as np
import pytest

from jaxstereo import JaxStereoError
from jaxstereo._stereo.evaluation import layer_errors, layer_table_markdown


def _points(true_z, error_m):
    points = np.zeros((true_z.size, 3))
    points[:, 2] = true_z + error_m
    return points


def test_layers_hold_their_points_errors():
    rng = np.random.default_rng(3)
    true_z = rng.uniform(0.0, 0.30, 20_000)
    error = rng.normal(0.0, 1e-3, true_z.size) + np.where(true_z < 0.18, 2e-3, 0.0)  # 2 mm low under 0.18 m water
    rows = layer_errors(_points(true_z, error), true_z, 0.18)
    depth = 0.18 - true_z
    assert [round(r["depth_from_m"], 2) for r in rows] == [-0.15, -0.10, -0.05, 0.0, 0.05, 0.10, 0.15]
    for r in rows:
        m = (depth >= r["depth_from_m"]) & (depth < r["depth_to_m"])
        assert r["n"] == m.sum()
        assert r["median_mm"] == pytest.approx(1e3 * np.median(error[m]))
        assert r["rmse_mm"] == pytest.approx(1e3 * np.sqrt(np.mean(error[m] ** 2)))
    assert all(abs(r["median_mm"] - 2.0) < 0.1 for r in rows if r["depth_from_m"] >= 0)


def test_two_surveys_of_other_depths_share_each_layer_once():
    # Layers once summed from each survey's shallowest point: -0.30 + 5 x 0.05 is not -0.05 to the last digit,
    # and the table then held "-0.05 to -0.00" and "-0.05 to +0.00" as two rows, each filled from both surveys.
    rng = np.random.default_rng(4)
    true_z = rng.uniform(0.0, 0.35, 10_000)
    results = {"low water": layer_errors(_points(true_z, 0.0), true_z, 0.05),
               "high water": layer_errors(_points(true_z, 0.0), true_z, 0.30)}
    rows = layer_table_markdown(results).splitlines()[2:]
    labels = [row.split("|")[1].strip() for row in rows]
    assert len(labels) == len(set(labels)) == 12  # -0.30 to +0.05 and -0.05 to +0.30
    assert "-0.05 to +0.00" in labels and "-0.05 to -0.00" not in labels


def test_no_known_point_is_refused():
    with pytest.raises(JaxStereoError, match="no point"):
        layer_errors(np.zeros((3, 3)), np.full(3, np.nan), 0.1)
    with pytest.raises(JaxStereoError, match="0 points"):
        layer_errors(np.zeros((0, 3)), np.zeros(0), 0.1)
