"""Feature-space matches of non-rigid ICP (core/correspond/features.py, beyond
the thesis, opt-in with `matching="features"`)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial import cKDTree

from shapegen_core.app.cli import build_parser
from shapegen_core.app.cli_common import settings_from_args
from shapegen_core.preprocess.collection import PrepareSettings, prepare_meshes
from shapegen_core.correspond import (Correspondence, CorrespondenceSettings, RegistrationProblem, correspond,
                                      pool, register)
from shapegen_core.correspond import data_terms, matching
from shapegen_core.correspond.features import (FALLBACK_SHARE, FIT_TOLERANCE, NO_REGION, TRIM, FeatureMatcher,
                                               agreement_weights, keeps_features, kept_matches, merged_regions,
                                               point_features, worse_fits)
from shapegen_core.correspond.settings import FEATURE_STIFFNESS, DataTermSettings, StiffnessSettings
from shapegen_core.demo_data import make_cups, make_vases
from shapegen_core.base.errors import ModelFileError
from shapegen_core.geometry import TargetSurface, closest_points_on_triangles, knn_graph, registration_frame
from shapegen_core.preprocess.landmarks import select_landmarks
from shapegen_core.app.fit_settings import FitSettings
from shapegen_core.base.settings import SettingsError, recorded_settings

#: every correspondence here starts from closest points, the start its figures were measured
#: from: these tests are about the data term, and on these procedural classes the automatic
#: start (the default) takes closest points too, after every shape's spectrum
CLOSEST = CorrespondenceSettings(data_term=DataTermSettings(initialisation="closest"))
FEATURES = CorrespondenceSettings(data_term=DataTermSettings(matching="features", feature_between=0.0,
                                                             initialisation="closest"))  # sides only
BETWEEN = CorrespondenceSettings(data_term=DataTermSettings(matching="features",
                                                            initialisation="closest"))  # positions between turning lines too


def _register(template, template_lm, target, target_lm, settings=FEATURES, **options):
    """Template landmarks → target surface in the template's registration frame; placed
    points back in the caller's coordinates, and the raw Registration."""
    centre, scale = registration_frame(template_lm.points)
    frame = lambda p: (np.asarray(p) - centre) / scale  # noqa: E731
    args = (frame(template_lm.points), knn_graph(template_lm.points, settings.stiffness.k_neighbours),
            TargetSurface(frame(target.vertices), target.faces), frame(target_lm.points), settings,
            template.face_normals()[template_lm.face_index], target.face_normals()[target_lm.face_index])
    result = register(RegistrationProblem(*args, **options))
    return result.placed.points * scale + centre, result, args


def test_point_features_closed_form():
    # w_n 0.5, w_u 1, h 0.01 (features.py); the normal compared by its horizontal direction
    settings = FEATURES
    normals = np.array([[0.0, 0.0, 3.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.6, -0.8]])
    features = point_features(normals, settings)
    expected = np.array([[0, 0, 0, np.tanh(100.0)], [0.5, 0, 0, 0.0], [0, 0, 0, 0], [0, 0.3, 0, np.tanh(-80.0)]])
    np.testing.assert_allclose(features, expected, atol=1e-15)
    between = np.array([0.0, 0.25, 0.5, 1.0])
    doubled = CorrespondenceSettings(data_term=DataTermSettings(matching="features", feature_between=2.0))
    with_between = point_features(normals, doubled, between)
    np.testing.assert_allclose(with_between, np.c_[expected, 2.0 * between], atol=1e-15)
    with pytest.raises(ValueError, match="between must hold one position per normal"):
        point_features(normals, doubled, between[:3])


def test_a_shape_matches_itself_exactly():
    # its landmarks are among the target samples with their own features: distance 0
    vase = make_vases(1, seed=3, resolution=(18, 18), pose=False)[0]
    landmarks = select_landmarks(vase.mesh, 300, seed=0)
    placed, _, _ = _register(vase.mesh, landmarks, vase.mesh, landmarks)
    assert np.abs(placed - landmarks.points).max() <= 1e-9 * vase.mesh.bbox_diagonal()


def test_matches_lie_on_the_face_of_the_chosen_sample():
    vase = make_vases(1, seed=5, resolution=(20, 28), pose=False)[0]
    landmarks = select_landmarks(vase.mesh, 100, seed=0)
    target = TargetSurface(vase.mesh.vertices, vase.mesh.faces)
    matcher = FeatureMatcher(target, landmarks.points, None, 100, FEATURES)
    points = landmarks.points + np.random.default_rng(0).normal(scale=0.01, size=landmarks.points.shape)
    goals, distance = matcher.forward(points, point_features(vase.mesh.face_normals()[landmarks.face_index], FEATURES))
    exact = target.closest(goals)  # every goal is a surface point, at least as far as the closest one
    assert exact.distance.max() <= 1e-12 * vase.mesh.bbox_diagonal()
    assert (distance >= target.closest(points).distance - 1e-12).all()
    np.testing.assert_allclose(distance, np.linalg.norm(goals - points, axis=1))


def test_remeshed_copy_corresponds_within_a_fraction_of_the_edge_length():
    coarse = make_vases(1, seed=3, resolution=(18, 18), pose=False)[0]
    fine = make_vases(1, seed=3, resolution=(40, 40), pose=False)[0]
    landmarks = select_landmarks(coarse.mesh, 300, seed=0)
    placed, _, _ = _register(coarse.mesh, landmarks, fine.mesh, select_landmarks(fine.mesh, 300, seed=1))
    truth = fine.points_at(coarse.surface_coordinates(landmarks.face_index, landmarks.barycentric))
    error = np.linalg.norm(placed - truth, axis=1).mean()
    # measured 0.308 edges; the softer end of the schedule (FEATURE_STIFFNESS 0.4) follows the
    # finer mesh more than α 5 did (0.218), the price of its lower error across shapes
    assert error < 0.35 * fine.mesh.mean_edge_length(), f"{error / fine.mesh.mean_edge_length():.3f} edges"


def test_a_warm_start_with_its_normals_converges_to_the_same_placement():
    a, b = make_vases(2, seed=6, resolution=(20, 28), pose=False)
    lm_a, lm_b = select_landmarks(a.mesh, 200, seed=0), select_landmarks(b.mesh, 200, seed=1)
    _, cold, args = _register(a.mesh, lm_a, b.mesh, lm_b)
    one_alpha = replace(BETWEEN, stiffness=StiffnessSettings(alpha_steps=1))
    warm = register(RegistrationProblem(*args[:4], one_alpha, *args[5:], initial_points=cold.deformed,
                                        initial_normals=cold.normals))
    scale = registration_frame(lm_a.points)[1]
    assert np.linalg.norm(warm.placed.points - cold.placed.points, axis=1).mean() < 0.1 * lm_a.radius / scale
    with pytest.raises(ValueError, match="initial_normals"):
        RegistrationProblem(*args, initial_points=cold.deformed, initial_normals=cold.normals[:-1])


def _true_error(shapes, prepared, result) -> float:
    """Mean distance of every landmark to its shape's point at the template landmark's
    true surface coordinates (s, θ), / bounding-box diagonal (shapes other than the template)."""
    t = result.names.index(result.template_name)
    template = prepared.landmarks[t]
    st = shapes[t].surface_coordinates(template.face_index, template.barycentric)
    return float(np.mean([np.linalg.norm(result.points_input[m] - shapes[m].points_at(st), axis=1).mean()
                          / shapes[m].mesh.bbox_diagonal() for m in range(len(shapes)) if m != t]))


@pytest.mark.quality
def test_feature_matches_lower_the_true_error_of_a_procedural_class():
    # measured with 150 landmarks: 3.65 % (closest points), 2.86 % (sides only, 0.78 of
    # closest), 2.65 % (with positions between turning lines, the default; 0.93 of sides
    # only); with 300 landmarks 2.74, 2.46 (0.90), 2.23 % (0.90), at 1.6 times the CPU.
    # How each step got there: docs/history.md, Correspondence: feature matches
    shapes = make_vases(5, seed=11, resolution=(33, 64))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=150, seed=0))
    error = lambda settings: _true_error(shapes, prepared, correspond(prepared, settings, jobs=1))  # noqa: E731
    closest = error(CLOSEST)
    sides_only = error(FEATURES)
    features = error(BETWEEN)
    assert sides_only < 0.97 * closest, f"features {sides_only:.4f} vs closest {closest:.4f}"
    assert features < 0.985 * sides_only, f"features {features:.4f} vs without positions between lines {sides_only:.4f}"


@pytest.mark.quality
def test_trimmed_matches_let_a_part_without_counterpart_follow_its_neighbours(monkeypatch):
    # seed 1's template (vase 2) has a neck; vase 1's lip (0.17) is narrower than its neck
    # (0.21), so its neck is no turning line and the template's neck-to-lip wall, facing
    # down, has no counterpart facing its way. Measured true error of vase 1: 4.03 % with
    # every match kept, 3.09 % with matches beyond 10 × the median distance dropped; the
    # other four 1.94 → 1.90 % on average (vase 4, also neckless, 3.22 → 3.11). Measured
    # without merged regions, which now match vase 1's upper wall plainly (then
    # 1.74 % with every match kept, 1.81 % trimmed); a part with no counterpart whose
    # regions do not merge (a handle, a spout) is still what trimming is for
    shapes = make_vases(6, seed=1, resolution=(65, 130))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=800, seed=0))
    assert shapes[1].params.lip_radius < shapes[1].params.neck_radius

    def errors(settings):
        result = correspond(prepared, settings, jobs=1)
        template = result.names.index(result.template_name)
        assert template == 2
        landmarks = prepared.landmarks[template]
        st = shapes[template].surface_coordinates(landmarks.face_index, landmarks.barycentric)
        return np.array([np.linalg.norm(result.points_input[m] - shapes[m].points_at(st), axis=1).mean()
                         / shapes[m].mesh.bbox_diagonal() for m in range(len(shapes))])

    monkeypatch.setattr(matching, "checks_regions", lambda settings: False)  # as measured: without merged regions
    trimmed = errors(FEATURES)
    monkeypatch.setattr(data_terms, "kept_matches", lambda distance: kept_matches(distance, 0.0))
    kept_all = errors(FEATURES)
    assert TRIM == 10.0
    assert trimmed[1] < 0.85 * kept_all[1], (trimmed[1], kept_all[1])
    others = [0, 3, 4, 5]
    assert trimmed[others].mean() <= 1.01 * kept_all[others].mean(), (trimmed[others], kept_all[others])


def test_kept_matches_drop_those_beyond_the_trim_times_the_median():
    distance = np.r_[np.full(90, 0.01), np.full(10, 0.5), np.inf]
    np.testing.assert_array_equal(kept_matches(distance, 10.0), np.r_[np.ones(90), np.zeros(11)])
    np.testing.assert_array_equal(kept_matches(distance, 0.0), np.ones(101))  # 0: none dropped (inf weighs 0 anyway)
    np.testing.assert_array_equal(kept_matches(np.zeros(5), 10.0), np.ones(5))  # a shape on itself
    np.testing.assert_array_equal(kept_matches(np.r_[np.zeros(5), 1e-10, 1e-3], 10.0), np.r_[np.ones(6), 0.0])


def test_the_first_registration_reports_positions_between_turning_lines():
    # the first registration has no template positions: it compares sides only and reports
    # the target's positions at its placed points; given those, a shape matches itself exactly
    vase = make_vases(1, seed=3, resolution=(18, 18), pose=False)[0]
    landmarks = select_landmarks(vase.mesh, 300, seed=0)
    _, first, args = _register(vase.mesh, landmarks, vase.mesh, landmarks, settings=BETWEEN)
    assert first.between is not None and first.between.shape == (len(landmarks.points),)  # about 300
    assert ((first.between >= 0) & (first.between <= 1)).all() and np.ptp(first.between) > 0.9
    again = register(RegistrationProblem(*args, template_between=first.between))
    np.testing.assert_allclose(again.between, first.between, atol=1e-12)
    assert np.abs(again.placed.points - first.placed.points).max() <= 1e-9
    with pytest.raises(ValueError, match="template_between"):
        RegistrationProblem(*args, template_between=first.between[:-1])
    off = register(RegistrationProblem(*args[:4], FEATURES, *args[5:], template_between=first.between))
    assert off.between is None  # not compared, not reported
    closest = register(RegistrationProblem(*args[:4], CorrespondenceSettings(), *args[5:]))
    assert closest.between is None


@pytest.fixture(scope="module")
def four_vases():
    """Four vases (seed 2) prepared with 150 landmarks."""
    shapes = make_vases(4, seed=2, resolution=(20, 28))
    return prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=150, seed=0))


@pytest.fixture(scope="module")
def four_vases_between(four_vases):
    """Their correspondence with positions between turning lines (BETWEEN), and every
    registration task it ran with that task's result, in order."""
    seen = []
    original = pool.register_task

    def recording(task, *args, **kwargs):
        result = original(task, *args, **kwargs)
        seen.append((task, result))
        return result

    with pytest.MonkeyPatch.context() as patched:
        patched.setattr(pool, "register_task", recording)
        return correspond(four_vases, BETWEEN, jobs=1), seen


@pytest.fixture(scope="module")
def three_vases():
    """Three vases (seed 2) prepared with 100 landmarks, and their BETWEEN correspondence."""
    shapes = make_vases(3, seed=2, resolution=(20, 28))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=100, seed=0))
    return prepared, correspond(prepared, BETWEEN, jobs=1)


def test_the_template_keeps_its_own_positions_and_each_shape_its_agreement(four_vases_between):
    result, seen = four_vases_between
    # the first round by feature matches, then by closest points for the fit check
    first_round, checked, second_round = seen[:4], seen[4:8], seen[8:]
    assert [task.settings.data_term.matching for task, _ in checked] == ["closest"] * 4
    assert not result.diagnostics.feature_fit_worse.any()
    assert all(task.template_between is None for task, _ in first_round) and len(second_round) == 4
    # the template's positions are the template shape's own, at its landmarks, for every shape
    template = result.names.index(result.template_name)
    own = first_round[template][1].between
    assert own.shape == (150,)
    for task, _ in second_round:
        np.testing.assert_array_equal(task.template_between, own)
    # each shape compares them with the weight its first-round agreement earned
    shares = agreement_weights(own, [r.between for _, r in first_round])
    assert shares[template] == 1.0
    for (task, _), share in zip(second_round, shares):
        assert task.settings.data_term.feature_between == BETWEEN.data_term.feature_between * share
    np.testing.assert_array_equal(result.diagnostics.between_shares, shares)  # recorded with the correspondence


def test_correspondence_files_record_each_shapes_share_of_the_positions(three_vases, tmp_path):
    prepared, result = three_vases
    shares = result.diagnostics.between_shares
    assert shares.shape == (3,) and ((shares >= 0) & (shares <= 1)).all()
    loaded = Correspondence.load(result.save(tmp_path / "c.npz"))
    np.testing.assert_array_equal(loaded.diagnostics.between_shares, result.diagnostics.between_shares)
    assert correspond(prepared, FEATURES, jobs=1).diagnostics.between_shares.shape == (0,)  # not compared: empty
    arrays = result.to_arrays()
    del arrays["between_shares"]  # a file written before the shares
    assert Correspondence.from_arrays(arrays, "old").diagnostics.between_shares.shape == (0,)
    _refused(arrays, "between_shares", (np.full(2, 0.5), np.array([0.5, 1.5, 0.0]), np.array([0.5, np.nan, 0.0])))


def test_agreement_weights_give_the_full_weight_to_agreement_and_none_to_unrelated_lines():
    rng = np.random.default_rng(0)
    template = rng.uniform(size=2000)
    shifted = lambda amount: np.clip(template + rng.choice([-amount, amount], size=2000), -1, 2)  # noqa: E731
    shares = agreement_weights(template, [template, shifted(0.05), shifted(0.15), shifted(0.3), rng.uniform(size=2000)])
    np.testing.assert_allclose(shares, [1.0, 1.0, 0.5, 0.0, 0.0])


def test_feature_matches_end_the_stiffness_schedule_softer():
    assert CorrespondenceSettings().alphas.tolist() == [100.0, 76.25, 52.5, 28.75, 5.0]  # the thesis's schedule
    assert FEATURE_STIFFNESS == 0.4
    np.testing.assert_allclose(FEATURES.alphas, np.linspace(100.0, 2.0, 5))
    one = replace(BETWEEN, stiffness=StiffnessSettings(alpha_end=10.0, alpha_steps=1))
    assert one.alphas.tolist() == [4.0]


def test_matching_setting_and_flag():
    assert CorrespondenceSettings().data_term.matching == "closest"  # the thesis stays the default
    assert BETWEEN.data_term.feature_between == 1.0  # with its positions between lines
    with pytest.raises(SettingsError, match="matching"):
        DataTermSettings(matching="nearest")
    for command in (["correspond", "x", "-o", "y"], ["fit", "x", "-o", "y"], ["evaluate", "x", "-o", "y"]):
        args = build_parser().parse_args(command + ["--matching", "features"])
        assert settings_from_args(CorrespondenceSettings, args).data_term.matching == "features"
        args = build_parser().parse_args(command + ["--matching", "features", "--feature-between", "0"])
        assert settings_from_args(CorrespondenceSettings, args).data_term.feature_between == 0.0
        args = build_parser().parse_args(command + ["--feature-between", "-1"])  # an error names the flag
        with pytest.raises(SettingsError, match=r"^--feature-between must be at least 0, got -1\.0$"):
            settings_from_args(CorrespondenceSettings, args)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["correspond", "x", "-o", "y", "--matching", "nearest"])


def test_files_written_before_feature_between_compared_sides_only():
    old = BETWEEN.as_dict()
    del old["data_term"]["feature_between"]
    assert recorded_settings(CorrespondenceSettings, {"settings": np.asarray(json.dumps(old))},
                             "old.npz").data_term.feature_between == 0
    flat = {"gamma": 2.0, "bidirectional_weight": 1.0, "matching": "features"}  # as older files record it
    assert CorrespondenceSettings.from_dict(flat, recorded=True).data_term.feature_between == 0
    # options given today (the panel's, the command line's) take today's default
    assert CorrespondenceSettings.from_dict({"matching": "features"}).data_term.feature_between == 1.0


REMOVED_KNOBS = {"feature_normals": 1.0, "feature_tilt": 1.0, "feature_up": 1.0, "feature_up_width": 0.1,
                 "feature_stiffness": 1.0, "feature_trim": 0.0, "feature_merged_regions": False,
                 "feature_samples": 20, "feature_fit_check": False, "feature_fallback_share": 0.1}


def test_files_that_record_removed_feature_knobs_load_as_today_and_new_settings_naming_them_are_refused(tmp_path):
    """The research knobs of feature matches are constants, not settings: a file that
    records them (as every file written before did) loads with today's constants; settings
    given now that name one are refused, naming it and why."""
    today = BETWEEN
    recorded = {**today.as_dict(), **REMOVED_KNOBS}
    assert recorded_settings(CorrespondenceSettings, {"settings": np.asarray(json.dumps(recorded))}, "old.npz") == today
    legacy = {"settings_keys": np.asarray(list(recorded)), "settings_values": np.asarray([repr(v) for v in recorded.values()])}
    assert recorded_settings(CorrespondenceSettings, legacy, "older.npz") == today  # key/value files too
    fit = FitSettings(correspondence=today).as_dict()
    fit["correspondence"].update(REMOVED_KNOBS)
    assert FitSettings.from_json(json.dumps(fit), recorded=True).correspondence == today  # inside model files
    for name, value in REMOVED_KNOBS.items():
        with pytest.raises(SettingsError, match=f"^{name} was removed: a research knob of feature matches"):
            CorrespondenceSettings.from_dict({"matching": "features", name: value})
        with pytest.raises(TypeError):
            CorrespondenceSettings(**{name: value})
    with pytest.raises(SettingsError, match=r"^correspondence\.feature_trim was removed"):
        FitSettings.from_dict({"correspondence": {"feature_trim": 10.0}})


def test_worse_fits_and_the_collection_rule():
    closest = np.array([0.04, 0.05, 0.05, 0.0, 1e-14])
    features = np.array([0.03, 0.05 * (1 + FIT_TOLERANCE) - 1e-6, 0.05 * (1 + FIT_TOLERANCE) + 1e-6, 1e-12, 0.0])
    np.testing.assert_array_equal(worse_fits(features, closest), [False, False, True, False, False])  # a shape on itself: 0 ≈ 0
    with pytest.raises(ValueError, match="one residual per shape"):
        worse_fits(features[:3], closest)
    assert FALLBACK_SHARE == 0.1
    assert keeps_features(np.zeros(10, bool)) and keeps_features(np.r_[True, np.zeros(9, bool)])
    assert not keeps_features(np.r_[True, True, np.zeros(8, bool)])  # 2 of 10 > 10 %
    assert keeps_features(np.zeros(0, bool))


def _unchecked(prepared, settings, monkeypatch):
    """The correspondence as without the fit check (its first round by feature matches only)."""
    with monkeypatch.context() as patched:
        patched.setattr(matching, "checks_fit", lambda settings: False)
        return correspond(prepared, settings, jobs=1)


@pytest.mark.quality
def test_cups_leaning_the_other_way_are_matched_by_closest_points_exactly(tmp_path, monkeypatch):
    # the template (cup 3) leans in (top radius 12 % below the bottom's); in the first round
    # feature matches collapse it onto part of the three cups leaning out by 12-21 % (residual
    # 1.55-1.65 × the closest-point fit's), so the collection is matched by closest points,
    # bit for bit
    prepared = prepare_meshes(make_cups(8, seed=1, rings=(8, 14)), PrepareSettings(n_landmarks=300, seed=0))
    closest = correspond(prepared, CLOSEST, jobs=1)
    checked = correspond(prepared, BETWEEN, jobs=1)
    unchecked = _unchecked(prepared, BETWEEN, monkeypatch)
    assert closest.template_name == checked.template_name == "cup_003"
    np.testing.assert_array_equal(checked.points, closest.points)
    np.testing.assert_array_equal(checked.face_index, closest.face_index)
    np.testing.assert_array_equal(checked.residuals, closest.residuals)
    worse = checked.diagnostics.feature_fit_worse
    assert worse.sum() >= 2 and not worse[checked.names.index("cup_003")]
    assert not checked.feature_matches_ran and unchecked.feature_matches_ran
    assert checked.matching_summary().startswith(f"closest points: feature matches fitted {int(worse.sum())} of 8")
    loaded = Correspondence.load(checked.save(tmp_path / "cups.npz"))
    np.testing.assert_array_equal(loaded.diagnostics.feature_fit_worse, worse)
    assert loaded.matching_summary() == checked.matching_summary()


def test_the_fit_check_changes_nothing_where_feature_matches_fit(four_vases, four_vases_between, monkeypatch):
    prepared, (checked, _) = four_vases, four_vases_between
    unchecked = _unchecked(prepared, BETWEEN, monkeypatch)
    np.testing.assert_array_equal(checked.points, unchecked.points)
    np.testing.assert_array_equal(checked.diagnostics.between_shares, unchecked.diagnostics.between_shares)
    np.testing.assert_array_equal(checked.diagnostics.feature_fit_worse, np.zeros(4, bool))
    assert checked.feature_matches_ran and checked.matching_summary().startswith("feature matches (they")
    assert unchecked.diagnostics.feature_fit_worse.shape == (0,) and unchecked.matching_summary().split(";")[0] == "feature matches"
    closest = correspond(prepared, CLOSEST, jobs=1)
    assert closest.diagnostics.feature_fit_worse.shape == (0,) and closest.matching_summary() == "closest points"
    assert not closest.feature_matches_ran


def test_files_before_the_fit_check_load_and_bad_records_are_refused(three_vases):
    arrays = three_vases[1].to_arrays()
    del arrays["feature_fit_worse"]
    old = Correspondence.from_arrays(arrays, "old")
    assert old.diagnostics.feature_fit_worse.shape == (0,) and old.feature_matches_ran
    _refused(arrays, "feature_fit_worse", (np.zeros(2, bool), np.zeros(3)))


def test_merged_regions_mark_template_regions_facing_opposite_ways_that_land_in_one():
    up, down = np.array([0.0, 0.3, 1.0]), np.array([0.0, 0.3, -1.0])
    template = np.repeat([0, 1, 2, 3, 4], [30, 30, 30, 30, 1])  # region 4: one point, below the minimum share
    normals = np.array([up] * 30 + [down] * 30 + [up] * 30 + [down] * 30 + [down])
    # 0 (up) and 1 (down) land in region 7 of the shape: merged; 2 (up) and 3 (down) in regions of their own
    shape = np.repeat([7, 7, 8, 9, 7], [30, 30, 30, 30, 1])
    expected = np.repeat([True, True, False, False, False], [30, 30, 30, 30, 1])
    np.testing.assert_array_equal(merged_regions(template, normals, shape), expected)
    # regions facing the same way that land in one region (a crease the shape rounds off) stay
    same = np.repeat([7, 8, 7, 9, 7], [30, 30, 30, 30, 1])
    assert not merged_regions(template, normals, same).any()
    # a region lands where most of its matches do; matches with no region known decide nothing
    mostly = shape.copy()
    mostly[30:40] = 8
    np.testing.assert_array_equal(merged_regions(template, normals, mostly), merged_regions(template, normals, shape))
    unknown = shape.copy()
    unknown[30:60] = NO_REGION
    assert not merged_regions(template, normals, unknown).any()
    assert not merged_regions(template, normals, template).any()  # a shape on itself
    with pytest.raises(ValueError, match="one region per template point"):
        merged_regions(template, normals, shape[:-1])


def test_plain_points_are_matched_by_position_and_normal_only():
    vase = make_vases(1, seed=3, resolution=(18, 18), pose=False)[0]
    landmarks = select_landmarks(vase.mesh, 200, seed=0)
    target = TargetSurface(vase.mesh.vertices, vase.mesh.faces)
    normals = vase.mesh.face_normals()[landmarks.face_index]
    matcher = FeatureMatcher(target, landmarks.points, normals, len(landmarks.points), FEATURES)
    rng = np.random.default_rng(1)
    points = landmarks.points + rng.normal(scale=0.02, size=landmarks.points.shape)
    features = point_features(normals, FEATURES)
    features[:, 3] = -features[:, 3]  # every up feature wrong: plain matches do not see it
    plain = np.zeros(len(points), dtype=bool)
    plain[::2] = True
    goals, _ = matcher.forward(points, features, plain)
    unmarked, _ = matcher.forward(points, features)
    np.testing.assert_array_equal(goals[~plain], unmarked[~plain])
    _, nearest = cKDTree(np.hstack([matcher.sample_points, matcher.sample_features[:, :3]])).query(
        np.hstack([points[plain], features[plain, :3]]))
    expected, _ = closest_points_on_triangles(points[plain], target.triangles[matcher.sample_faces[nearest]])
    np.testing.assert_array_equal(goals[plain], expected)
    # backward: every template point plain is the nearest by position and normal
    every = np.ones(len(points), dtype=bool)
    nearest, _ = matcher.backward(points, features, every)
    _, expected = cKDTree(np.hstack([points, features[:, :3]])).query(
        np.hstack([matcher.landmarks, matcher.landmark_features[:, :3]]))
    np.testing.assert_array_equal(nearest, expected)
    np.testing.assert_array_equal(matcher.backward(points, features, ~every)[0], matcher.backward(points, features)[0])


@pytest.mark.quality
def test_a_vase_without_a_neck_is_matched_plainly_where_its_regions_merge(tmp_path, monkeypatch):
    # seed 1: the template (vase 2) has a neck; vases 1 and 4 have none, so belly to rim
    # faces up on them in one piece where the template's neck splits it. Measured true
    # error here (400 landmarks): vase 1 3.34 -> 1.52 %, vase 4 3.13 -> 2.15 %, the others
    # unchanged; 800 landmarks: docs/history.md, Measurements behind the correspondence settings
    shapes = make_vases(6, seed=1, resolution=(65, 130))
    prepared = prepare_meshes([s.mesh for s in shapes], PrepareSettings(n_landmarks=400, seed=0))
    neckless = [i for i, s in enumerate(shapes) if s.params.lip_radius < s.params.neck_radius]
    assert neckless == [1, 4]
    checked = correspond(prepared, BETWEEN, jobs=1)
    with monkeypatch.context() as patched:
        patched.setattr(matching, "checks_regions", lambda settings: False)
        unchecked = correspond(prepared, BETWEEN, jobs=1)
    assert checked.template_name == unchecked.template_name == "vase_002"
    np.testing.assert_array_equal(np.flatnonzero(checked.diagnostics.plain_shares), neckless)
    assert (checked.diagnostics.plain_shares[neckless] > 0.3).all()
    others = [i for i in range(6) if i not in neckless]
    np.testing.assert_array_equal(checked.points[others], unchecked.points[others])
    error = lambda result: np.array([_shape_error(shapes, prepared, result, m) for m in neckless])  # noqa: E731
    assert (error(checked) < 0.85 * error(unchecked)).all(), (error(checked), error(unchecked))
    assert "template regions merged on 2 of 6 shapes" in checked.matching_summary()
    assert unchecked.diagnostics.plain_shares.shape == (0,) and "merged" not in unchecked.matching_summary()
    loaded = Correspondence.load(checked.save(tmp_path / "c.npz"))
    np.testing.assert_array_equal(loaded.diagnostics.plain_shares, checked.diagnostics.plain_shares)
    arrays = checked.to_arrays()
    del arrays["plain_shares"]  # a file written before the check
    assert Correspondence.from_arrays(arrays, "old").diagnostics.plain_shares.shape == (0,)
    _refused(arrays, "plain_shares", (np.full(5, 0.5), np.r_[np.zeros(5), 1.5]))


def _refused(arrays: dict, key: str, wrong_values) -> None:
    """Each of `wrong_values` in place of a correspondence file's `key` is refused, naming it."""
    for wrong in wrong_values:
        arrays[key] = wrong
        with pytest.raises(ModelFileError, match=key):
            Correspondence.from_arrays(arrays, "bad")


def _shape_error(shapes, prepared, result, m: int) -> float:
    """Shape m's mean distance to its points at the template landmarks' true (s, θ), / diagonal."""
    t = result.names.index(result.template_name)
    landmarks = prepared.landmarks[t]
    st = shapes[t].surface_coordinates(landmarks.face_index, landmarks.barycentric)
    return float(np.linalg.norm(result.points_input[m] - shapes[m].points_at(st), axis=1).mean()
                 / shapes[m].mesh.bbox_diagonal())
