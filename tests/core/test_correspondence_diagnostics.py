"""The correspondence and its optional record of how it came about (`Correspondence.diagnostics`):
a correspondence without the record saves and loads without it, one with it round-trips,
and files of before (every file held the ICP iterations) load with the record they hold."""

from __future__ import annotations

import numpy as np
import pytest

from shapegen_core.base.errors import ModelFileError
from shapegen_core.base.npzfile import save_npz
from shapegen_core.correspond import (CORRESPONDENCE_FORMAT, CORRESPONDENCE_VERSION, Correspondence,
                                      CorrespondenceDiagnostics, CorrespondenceSettings)

SHAPES, LANDMARKS = 3, 5


def _correspondence(diagnostics=None) -> Correspondence:
    rng = np.random.default_rng(0)
    points = rng.normal(size=(SHAPES, LANDMARKS, 3))
    return Correspondence(
        names=["a", "b", "c"], points=points, points_input=points.copy(),
        face_index=np.zeros((SHAPES, LANDMARKS), dtype=np.int64),
        barycentric=np.full((SHAPES, LANDMARKS, 3), 1 / 3), edges=np.array([[0, 1], [1, 2]]),
        template_points=points[0].copy(), template_name="a", transforms=np.tile(np.eye(4), (SHAPES, 1, 1)),
        residuals=np.full(SHAPES, 0.01), outliers=np.zeros(SHAPES, dtype=bool), outlier_reasons=["", "", ""],
        # closest points named, as every file without the record ran them (auto records its choice)
        settings=CorrespondenceSettings.from_dict({"initialisation": "closest"}), diagnostics=diagnostics)


def _saved(arrays: dict, path) -> Correspondence:
    return Correspondence.load(save_npz(path, CORRESPONDENCE_FORMAT, CORRESPONDENCE_VERSION, arrays))


def test_a_correspondence_without_diagnostics_saves_and_loads_without_them(tmp_path):
    plain = _correspondence()
    loaded = Correspondence.load(plain.save(tmp_path / "plain.npz"))
    assert loaded.diagnostics is None
    np.testing.assert_array_equal(loaded.points, plain.points)
    # read as files of before read: nothing recorded
    assert loaded.start_used == "closest" and loaded.matching_summary() == "closest points"
    assert loaded.pose_summary() == "" and loaded.recorded.shape_starts == []


def test_diagnostics_round_trip_and_a_run_without_refinement_writes_none(tmp_path):
    record = CorrespondenceDiagnostics(iterations=np.array([3, 4, 5]), start="spectral", start_reason="asked for",
                                       shape_starts=["template", "spectral", "closest"], pose_notes=["", "posed", ""])
    arrays = _correspondence(record).to_arrays()
    assert "refinement" not in arrays and "refinement_trace" not in arrays
    loaded = _saved(arrays, tmp_path / "c.npz").diagnostics
    np.testing.assert_array_equal(loaded.iterations, [3, 4, 5])
    assert (loaded.start, loaded.start_reason, loaded.shape_starts, loaded.pose_notes) == \
        ("spectral", "asked for", ["template", "spectral", "closest"], ["", "posed", ""])
    assert loaded.refinement == "none" and loaded.refinement_trace.shape == (0, 3)


def test_a_file_written_while_population_refinement_was_an_option_still_loads(tmp_path):
    arrays = _correspondence(CorrespondenceDiagnostics(iterations=np.array([3, 4, 5]))).to_arrays()
    arrays["refinement"] = np.asarray("population")
    arrays["refinement_trace"] = np.array([[2.0, 1.5, 0.5], [1.8, 1.4, 0.4]])
    settings = CorrespondenceSettings().to_json()[:-1] + ', "refinement": {"method": "population", "iterations": 3}}'
    arrays["settings"] = np.asarray(settings)
    loaded = _saved(arrays, tmp_path / "refined.npz")
    assert loaded.diagnostics.refinement == "population" and len(loaded.diagnostics.refinement_trace) == 2
    assert loaded.settings == CorrespondenceSettings()  # the option is gone; its record is kept
    arrays["refinement"] = np.asarray("sideways")
    with pytest.raises(ModelFileError, match="unknown refinement 'sideways'"):
        _saved(arrays, tmp_path / "bad.npz")


def test_a_record_of_the_wrong_length_is_refused(tmp_path):
    arrays = _correspondence(CorrespondenceDiagnostics(iterations=np.array([3, 4, 5]))).to_arrays()
    arrays["iterations"] = np.array([3, 4])
    with pytest.raises(ModelFileError, match="iterations must be empty or one count per shape"):
        _saved(arrays, tmp_path / "bad.npz")
