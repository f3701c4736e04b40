import numpy as np
import onnx
import pytest
from onnx_models import linear_model, save
from symmetry_cases import CASES

from popcode_runtime import (
    CodeLayout,
    ModelMetadata,
    PopcodeError,
    PopulationCode,
    PoseEstimator,
    Representation,
    RotationFrame,
    symmetry_rotations,
)
from popcode_runtime.geometry.rotations import (
    geodesic_angle,
    matrix_to_quaternion,
    matrix_to_sixd,
    quaternion_to_matrix,
    random_rotations,
    ray_rotation,
    rotation_between,
    rotvec_to_matrix,
)
from popcode_runtime.model.decoding import quaternion_mean_shift

LAYOUT = CodeLayout(n_axes=642, n_angles=36)
K = [1075.65, 1073.90, 360.0, 270.0]
BOXES = [[100.0, 120.0, 90.0, 80.0], [400.0, 300.0, 150.0, 120.0], [650.0, 500.0, 100.0, 100.0]]


def metadata(**overrides) -> ModelMetadata:
    fields = {"representation": Representation.POPULATION_CODE, "code": LAYOUT, "objects": {5: CASES["two_fold"]},
              "training": {"dataset": "unit-test"}}
    fields.update(overrides)
    return ModelMetadata(**fields)


@pytest.fixture
def R_known():
    return random_rotations(1, np.random.default_rng(5))[0]


@pytest.fixture
def scene():
    return np.random.default_rng(1).integers(0, 256, size=(540, 720), dtype=np.uint8)


@pytest.fixture
def code_model(tmp_path, R_known):
    bias = PopulationCode(LAYOUT).encode(R_known, symmetry_rotations(CASES["two_fold"]))
    return save(linear_model(bias, metadata=metadata()), tmp_path / "code.onnx")


def test_predict_decodes_the_models_code(code_model, R_known, scene):
    estimator = PoseEstimator(code_model)
    predictions = estimator.predict(scene, BOXES[:1], return_code=True)
    assert len(predictions) == 1
    p = predictions[0]
    np.testing.assert_allclose(p.R_m2c, PopulationCode(LAYOUT).decode(p.code).R[0])
    S = symmetry_rotations(CASES["two_fold"])
    assert np.degrees(geodesic_angle(p.R_m2c, R_known @ S).min()) < 12.0
    assert p.score == pytest.approx(float(p.code.max()))
    np.testing.assert_allclose(p.R_m2c @ p.R_m2c.T, np.eye(3), atol=1e-9)
    assert estimator.providers == ["CPUExecutionProvider"]


def test_batched_prediction_equals_one_by_one(tmp_path, scene):
    bias = np.zeros(LAYOUT.size, np.float32)
    model = save(linear_model(bias, weight_scale=1.0, metadata=metadata()), tmp_path / "m.onnx")
    estimator = PoseEstimator(model, threads=1)
    batched = estimator.predict(scene, BOXES, return_code=True)
    for box, together in zip(BOXES, batched, strict=True):
        alone = estimator.predict(scene, [box], return_code=True)[0]
        np.testing.assert_allclose(together.code, alone.code, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(together.R_m2c, alone.R_m2c)
    # Different boxes see different pixels, so the outputs differ.
    assert not np.allclose(batched[0].code, batched[1].code)


def test_allocentric_model_needs_K_and_converts_back(tmp_path, R_known, scene):
    bias = PopulationCode(LAYOUT).encode(R_known)
    model = save(linear_model(bias, metadata=metadata(rotation_frame=RotationFrame.ALLOCENTRIC,
                                                      objects={1: CASES["none"]})), tmp_path / "allo.onnx")
    estimator = PoseEstimator(model)
    with pytest.raises(PopcodeError, match="camera matrix K"):
        estimator.predict(scene, BOXES[:2])
    predictions = estimator.predict(scene, BOXES[:2], K=K)
    R_allo = PopulationCode(LAYOUT).decode(bias).R[0]
    Km = np.array([[K[0], 0, K[2]], [0, K[1], K[3]], [0, 0, 1]])
    for box, p in zip(BOXES[:2], predictions, strict=True):
        centre = [box[0] + box[2] / 2, box[1] + box[3] / 2]
        np.testing.assert_allclose(p.R_m2c, ray_rotation(Km, centre) @ R_allo, atol=1e-12)
    with pytest.raises(PopcodeError, match="camera matrix"):
        estimator.predict(scene, BOXES[:1], K=[-1, 1, 0, 0])


def test_single_variable_models_decode_exactly(tmp_path, R_known, scene):
    sixd = matrix_to_sixd(R_known).astype(np.float32)
    model = save(linear_model(sixd, metadata=metadata(representation=Representation.SINGLE_VARIABLE,
                                                      objects={1: CASES["none"]})), tmp_path / "sixd.onnx")
    np.testing.assert_allclose(PoseEstimator(model).predict(scene, BOXES[:1])[0].R_m2c, R_known, atol=1e-6)

    axis_layout = CodeLayout(n_axes=642, axis_only=True, symmetry_axis=(0, 0, 1))
    direction = R_known @ np.array([0.0, 0.0, 1.0])
    model = save(linear_model(direction.astype(np.float32) * 3,
                              metadata=metadata(representation=Representation.SINGLE_VARIABLE, code=axis_layout,
                                                objects={2: CASES["continuous"]})), tmp_path / "axis.onnx")
    R = PoseEstimator(model).predict(scene, BOXES[:1])[0].R_m2c
    np.testing.assert_allclose(R @ [0, 0, 1], direction, atol=1e-6)
    np.testing.assert_allclose(R, rotation_between(np.array([0, 0, 1.0]), direction), atol=1e-6)


def jittered_quaternions(R: np.ndarray, count: int, rng: np.random.Generator, max_deg: float = 2.0) -> np.ndarray:
    """``count`` quaternions of rotations within about ``max_deg`` of ``R``."""
    small = rotvec_to_matrix(rng.normal(size=(count, 3)) * np.deg2rad(max_deg) / 2)
    return matrix_to_quaternion(R @ small)


def test_multi_hypothesis_mean_shift_picks_the_largest_cluster(tmp_path, scene):
    rng = np.random.default_rng(2)
    R_main, R_other = random_rotations(2, rng)
    quats = np.concatenate([jittered_quaternions(R_main, 6, rng), jittered_quaternions(R_other, 2, rng)])
    quats[:3] *= -1  # q and -q are the same rotation: sign flips must not split a cluster
    mean, share = quaternion_mean_shift(quats)
    assert share == pytest.approx(0.75)
    assert np.degrees(geodesic_angle(quaternion_to_matrix(mean), R_main)) < 2.0
    model = save(linear_model(quats.reshape(-1).astype(np.float32),
                              metadata=metadata(representation=Representation.MULTI_HYPOTHESIS, num_hypotheses=8,
                                                objects={1: CASES["none"]})), tmp_path / "mh.onnx")
    p = PoseEstimator(model).predict(scene, BOXES[:1])[0]
    assert np.degrees(geodesic_angle(p.R_m2c, R_main)) < 2.0 and p.score == pytest.approx(0.75)


def test_model_without_metadata_is_refused(tmp_path, R_known):
    bias = PopulationCode(LAYOUT).encode(R_known)
    model = save(linear_model(bias), tmp_path / "plain.onnx")
    with pytest.raises(PopcodeError, match="not a popcode model"):
        PoseEstimator(model)


def test_metadata_inconsistent_with_output_is_refused(tmp_path, R_known):
    bias = PopulationCode(LAYOUT).encode(R_known)
    model = linear_model(bias, output_dim=500)
    onnx.helper.set_model_props(model, metadata().to_props())
    with pytest.raises(PopcodeError, match="500 values per crop"):
        PoseEstimator(save(model, tmp_path / "bad.onnx"))


def test_malformed_metadata_names_the_key(tmp_path, R_known):
    model = linear_model(PopulationCode(LAYOUT).encode(R_known))
    props = metadata().to_props()
    props["popcode.code"] = "{not json"
    onnx.helper.set_model_props(model, props)
    with pytest.raises(PopcodeError, match="popcode.code"):
        PoseEstimator(save(model, tmp_path / "bad.onnx"))
    del props["popcode.representation"]
    props["popcode.code"] = metadata().to_props()["popcode.code"]
    onnx.helper.set_model_props(model, props)
    with pytest.raises(PopcodeError, match="popcode.representation"):
        PoseEstimator(save(model, tmp_path / "bad2.onnx"))


def test_mixing_continuous_and_discrete_objects_is_refused():
    with pytest.raises(PopcodeError, match="continuous"):
        metadata(objects={1: CASES["continuous"], 2: CASES["two_fold"]})


@pytest.mark.parametrize("points", [[[0.0, 0.0, 0.0]] * 3, [[0.0, 0.0]] * 8, [["a", 1, 2]] * 4,
                                    [[0.0, float("nan"), 0.0]] * 4])
def test_malformed_hull_points_are_refused_at_load(points):
    with pytest.raises(PopcodeError, match="object 1: hull_points_mm must be"):
        metadata(objects={1: {**CASES["two_fold"], "hull_points_mm": points}})
    tetrahedron = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert metadata(objects={1: {**CASES["two_fold"], "hull_points_mm": tetrahedron}})


@pytest.mark.parametrize("points", [[[1.0, 2.0, 3.0]] * 4, [[0.0, 0.0, z] for z in range(5)],
                                    [[x, y, 0.0] for x in (0, 1) for y in (0, 1)]])
def test_degenerate_hull_points_are_refused_at_load(points):
    """Identical, collinear or coplanar points fit any box at some distance: a silent wrong translation."""
    with pytest.raises(PopcodeError, match="object 1: hull_points_mm are degenerate"):
        metadata(objects={1: {**CASES["two_fold"], "hull_points_mm": points}})


def test_corrupt_or_missing_model_file(tmp_path, code_model):
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(code_model.read_bytes()[:200])
    with pytest.raises(PopcodeError, match="cannot load"):
        PoseEstimator(corrupt)
    with pytest.raises(PopcodeError, match="not found"):
        PoseEstimator(tmp_path / "nothing.onnx")


def test_unavailable_provider_is_named(code_model):
    with pytest.raises(PopcodeError, match="not available"):
        PoseEstimator(code_model, providers=["definitely-not-a-provider"])


def test_bad_images_and_boxes(code_model, scene):
    estimator = PoseEstimator(code_model)
    with pytest.raises(PopcodeError, match="NaN"):
        estimator.predict(np.full((50, 50), np.nan, np.float32), [[0, 0, 10, 10]])
    with pytest.raises(PopcodeError, match="wholly outside"):
        estimator.predict(scene, [[2000, 0, 10, 10]])
    with pytest.raises(PopcodeError, match="no boxes"):
        estimator.predict(scene, [])
    with pytest.raises(PopcodeError, match="float32"):
        estimator.run(np.zeros((1, 1, 128, 128), np.float64))
