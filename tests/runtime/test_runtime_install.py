"""The runtime installs alone: a fresh virtual environment, ``pip install ./runtime``, no torch."""

import json
import subprocess
import sys
import venv
from pathlib import Path

import cv2
import numpy as np
import pytest
from hostile_files import write_hostile_files
from onnx_models import linear_model, save
from symmetry_cases import CASES

from popcode_runtime import (
    CodeLayout,
    ModelMetadata,
    PopulationCode,
    PoseEstimator,
    Representation,
    read_image,
    symmetry_rotations,
)
from popcode_runtime.geometry.rotations import geodesic_angle, random_rotations

RUNTIME_DIR = Path(__file__).resolve().parents[2] / "runtime"
MODELS = RUNTIME_DIR.parent / "models"
TESTS = Path(__file__).resolve().parents[1]
CATALOGUE = ("import json, sys; from pathlib import Path; sys.path.insert(0, sys.argv[1]);"
             "from hostile_cases import catalogue_problems; print(json.dumps(catalogue_problems(Path(sys.argv[2]))))")
TRAINER_ONLY = {"torch", "onnx", "trimesh", "pyrender", "matplotlib", "scipy", "popcode-trainer"}
REQUIRES = (
    "import importlib.metadata as m, re;"
    "print('\\n'.join(re.split(r'[ ;<>=!~\\[]', r, maxsplit=1)[0] for r in m.requires('popcode-runtime')"
    " if 'extra ==' not in r))"  # the optional extras (depth) are not installed by pip install ./runtime
)


def _samples_split(folder: Path) -> tuple[Path, Path]:
    """The shipped samples as a one-scene BOP split (images and cameras) and their boxes as BOP detections."""
    samples = json.loads((MODELS / "samples" / "samples.json").read_text())["samples"]
    (folder / "000001" / "gray").mkdir(parents=True)
    cameras, detections = {}, []
    for im_id, sample in enumerate(samples):
        image = cv2.imread(str(MODELS / "samples" / sample["image"]), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(folder / "000001" / "gray" / f"{im_id:06d}.png"), image)
        fx, fy, cx, cy = sample["K"]
        cameras[str(im_id)] = {"cam_K": [fx, 0, cx, 0, fy, cy, 0, 0, 1], "depth_scale": 1.0}
        detections.append({"scene_id": 1, "image_id": im_id, "category_id": sample["obj_id"], "bbox": sample["box"],
                           "score": 1.0, "time": 0.0})
    (folder / "000001" / "scene_camera.json").write_text(json.dumps(cameras))
    (folder / "detections.json").write_text(json.dumps(detections))
    return folder, folder / "detections.json"


@pytest.mark.slow
def test_runtime_installs_and_predicts_without_torch(tmp_path):
    env_dir = tmp_path / "env"
    venv.create(env_dir, with_pip=True)
    python = env_dir / "bin" / "python"
    # No byte-compiling of what pip installs (numpy, onnxruntime, OpenCV): the calls below import little of it.
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--no-compile", str(RUNTIME_DIR)], check=True)

    listed = subprocess.run([str(python), "-m", "pip", "list", "--format=json"], check=True,
                            capture_output=True, text=True).stdout
    installed = {package["name"].lower() for package in json.loads(listed)}
    assert not installed & TRAINER_ONLY, f"trainer-side packages installed: {installed & TRAINER_ONLY}"
    requires = subprocess.run([str(python), "-c", REQUIRES], check=True, capture_output=True, text=True).stdout
    assert set(requires.split()) == {"numpy", "onnxruntime", "opencv-python-headless"}

    R = random_rotations(1, np.random.default_rng(9))[0]
    layout = CodeLayout(n_axes=642, n_angles=36)
    S = symmetry_rotations(CASES["two_fold"])
    meta = ModelMetadata(representation=Representation.POPULATION_CODE, code=layout, objects={3: CASES["two_fold"]})
    model = save(linear_model(PopulationCode(layout).encode(R, S), metadata=meta), tmp_path / "m.onnx")
    image = tmp_path / "scene.png"
    cv2.imwrite(str(image), np.zeros((100, 120), np.uint8))

    popcode = env_dir / "bin" / "popcode"
    result = subprocess.run([str(popcode), "predict", str(model), str(image), "--box", "20,20,50,40", "--json"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    R_pred = np.array(json.loads(result.stdout)["predictions"][0]["R_m2c"])
    assert np.degrees(geodesic_angle(R_pred, R @ S).min()) < 12.0

    # The shipped model runs on its sample image with the runtime alone, as the README shows.
    shipped = MODELS / "builtin-parts-3-6.onnx"
    sample = next(s for s in json.loads((MODELS / "samples" / "samples.json").read_text())["samples"]
                  if s["obj_id"] == 3)
    box, K = (",".join(f"{v:g}" for v in sample[key]) for key in ("box", "K"))  # K: allocentric models need it
    picture = tmp_path / "estimate.png"
    result = subprocess.run([str(popcode), "predict", str(shipped), str(MODELS / "samples" / sample["image"]),
                             "--box", box, "--K", K, "--obj-id", "3", "--top-k", "2", "--json", "--draw", str(picture)],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    assert cv2.imread(str(picture)).shape == (128, 128, 3)  # the picture of the estimate, drawn by the runtime alone
    R_venv = np.array(json.loads(result.stdout)["predictions"][0]["R_m2c"])
    assert 0.0 <= json.loads(result.stdout)["predictions"][0]["confidence"] <= 1.0  # the shipped calibrator
    R_here = PoseEstimator(shipped).predict(read_image(MODELS / "samples" / sample["image"]), [sample["box"]],
                                              K=sample["K"])[0].R_m2c
    assert np.allclose(R_venv, R_here, atol=1e-5)

    # popcode run over a BOP split of the shipped samples and their boxes as detections, with the runtime alone.
    split, detections = _samples_split(tmp_path / "split")
    results = tmp_path / "results.csv"
    result = subprocess.run([str(popcode), "run", str(MODELS / "builtin-parts-1-2.onnx"), str(shipped), "--split",
                             str(split), "--detections", str(detections), "--out", str(results), "--quiet"],
                            capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    lines = results.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time" and [line.split(",")[2] for line in lines[1:]] == \
        [str(obj_id) for obj_id in range(1, 7)]

    failing = subprocess.run([str(popcode), "info", str(tmp_path / "missing.onnx")], capture_output=True, text=True)
    assert failing.returncode == 2 and "not found" in failing.stderr and "Traceback" not in failing.stderr

    # popcode bag needs the ros extra (rosbags, foxglove-sdk): without it, the line that says how to install it.
    bag = subprocess.run([str(popcode), "bag", str(shipped), "--bag", str(tmp_path / "recorded"), "--detector",
                          str(MODELS / "builtin-parts-detector.onnx"), "--image-topic", "/image", "--camera-info-topic",
                          "/camera_info", "--out", str(tmp_path / "poses")], capture_output=True, text=True)
    assert bag.returncode == 2 and "pip install ./runtime[ros]" in bag.stderr and "Traceback" not in bag.stderr

    # The hostile-input catalogue (issue 19) holds with the runtime alone too.
    hostile = write_hostile_files(tmp_path / "hostile")
    report = subprocess.run([str(python), "-c", CATALOGUE, str(TESTS), str(hostile)], check=True,
                            capture_output=True, text=True).stdout
    assert json.loads(report) == {}
    assert sys.executable != str(python)
