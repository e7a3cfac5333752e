"""The survey `.npz` written in steps (`SurveyWriter`): the file `np.savez` writes, whatever the steps."""

import numpy as np
import pytest

from jaxstereo import JaxStereoError
from jaxstereo._stereo.survey import Survey, SurveyWriter, load_survey, save_survey


def _survey(n: int = 1000, seed: int = 0) -> Survey:
    rng = np.random.default_rng(seed)
    return Survey(rng.normal(size=(n, 3)), rng.integers(0, 256, (n, 3)).astype(np.uint8),
                  rng.uniform(0, 1000, (n, 2)), rng.random(n) < 0.5, '{"rig": 1}', "exact", 0.165,
                  rng.random((n, 6)).astype(np.float32), *(rng.random(n).astype(np.float32) for _ in range(3)))


def _savez(survey: Survey, path) -> None:
    """The survey file as `np.savez` writes it: the reference."""
    np.savez(path, points=survey.points, colors=survey.colors, pixels=survey.pixels.astype(np.float32),
             submerged=survey.submerged, rig=np.array(survey.rig_json), model=np.array(survey.model),
             water_level=np.array(survey.water_level), cov=survey.cov, sigma_z_match=survey.sigma_z_match,
             sigma_z_level=survey.sigma_z_level, dz_subpixel=survey.dz_subpixel)


def test_points_then_covariance_rows_then_the_rest_give_np_savez_file(tmp_path):
    survey = _survey()
    _savez(survey, tmp_path / "reference.npz")
    save_survey(survey, tmp_path / "saved.npz")
    writer = SurveyWriter(tmp_path / "steps.npz")
    writer.write_points(survey)
    fields = {"cov": survey.cov}
    for start in range(0, 1000, 300):  # rows in chunks, the last one short
        writer.error_rows(fields, start, min(start + 300, 1000))
    assert not (tmp_path / "steps.npz").exists()  # under a temporary name until finished
    writer.finish(survey)
    reference = (tmp_path / "reference.npz").read_bytes()
    assert (tmp_path / "saved.npz").read_bytes() == reference
    assert (tmp_path / "steps.npz").read_bytes() == reference
    np.testing.assert_array_equal(load_survey(tmp_path / "steps.npz").cov, survey.cov)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reference.npz", "saved.npz", "steps.npz"]


def test_rows_out_of_order_or_other_covariances_are_refused_and_discard_leaves_nothing(tmp_path):
    survey = _survey()
    writer = SurveyWriter(tmp_path / "s.npz")
    writer.write_points(survey)
    writer.error_rows({"cov": survey.cov}, 0, 500)
    with pytest.raises(JaxStereoError, match="rows 600:1000 came after 500 rows"):
        writer.error_rows({"cov": survey.cov}, 600, 1000)
    writer.error_rows({"cov": survey.cov}, 500, 1000)
    other = Survey(*(getattr(survey, f) for f in ("points", "colors", "pixels", "submerged", "rig_json", "model",
                                                   "water_level")), survey.cov + 1, survey.sigma_z_match,
                   survey.sigma_z_level, survey.dz_subpixel)
    with pytest.raises(JaxStereoError, match="not the survey's"):
        writer.finish(other)
    writer.discard()
    assert list(tmp_path.iterdir()) == []
