"""Write the files that the hostile-input catalogue (``hostile_cases``) names: bad models, bad images.

Needs onnx to build models, so it runs in the test environment; the runtime-only
venv test reads the files it wrote.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import onnx
from hostile_cases import DEPTH_MM, DEPTH_OBJECT, GOOD_K_LIST, IMAGE_SHAPE, LAYOUT, METADATA_CASES, OBJECT
from onnx import TensorProto, helper
from onnx_models import ONNX_IR_VERSION, ONNX_OPSET, linear_model

from popcode_runtime import ModelMetadata, PopulationCode, Representation, parse_camera_matrix, symmetry_rotations
from popcode_runtime.geometry.rotations import matrix_to_sixd, random_rotations
from popcode_runtime.model.metadata import INPUT_NAME, OUTPUT_NAME

_NON_UTF8_MARK = "Z" * 16


def _metadata() -> ModelMetadata:
    return ModelMetadata(representation=Representation.POPULATION_CODE, code=LAYOUT, objects={7: OBJECT},
                         training={"dataset": "hostile"})


def _bias() -> np.ndarray:
    R = random_rotations(1, np.random.default_rng(19))[0]
    return PopulationCode(LAYOUT).encode(R, symmetry_rotations(OBJECT))


def _with_props(props: dict[str, str]) -> onnx.ModelProto:
    model = linear_model(_bias(), weight_scale=0.1)
    helper.set_model_props(model, props)
    return model


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_header(width: int, height: int) -> bytes:
    """A PNG signature and IHDR claiming ``width x height`` (no pixel data follows)."""
    return b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))


def _png_claiming(width: int, height: int) -> bytes:
    """A well-formed PNG (IHDR, a tiny IDAT, IEND) claiming ``width x height``: OpenCV reads the header, then checks
    its own pixel limit before it decodes."""
    return (_png_header(width, height) + _png_chunk(b"IDAT", zlib.compress(b"\x00" * 64))
            + _png_chunk(b"IEND", b""))


def _jpeg_header(width: int, height: int) -> bytes:
    """SOI, an APP0 segment and a baseline SOF0 claiming ``width x height``."""
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00"
    sof0 = b"\xff\xc0" + struct.pack(">HBHHB", 11, 8, height, width, 1) + b"\x01\x11\x00"
    return b"\xff\xd8" + app0 + sof0


def _runtime_failure_model() -> onnx.ModelProto:
    """Valid signature and metadata, but a Reshape to a shape that only fits a batch of 3: fails at run time."""
    width = LAYOUT.size
    nodes = [
        helper.make_node("ReduceMean", [INPUT_NAME], ["mean"], axes=[1, 2, 3], keepdims=0),
        helper.make_node("Reshape", ["mean", "shape"], ["row"]),
        helper.make_node("Expand", ["row", "full"], [OUTPUT_NAME]),
    ]
    graph = helper.make_graph(
        nodes, "run_fails",
        [helper.make_tensor_value_info(INPUT_NAME, TensorProto.FLOAT, ["N", 1, 128, 128])],
        [helper.make_tensor_value_info(OUTPUT_NAME, TensorProto.FLOAT, ["N", width])],
        initializer=[helper.make_tensor("shape", TensorProto.INT64, [2], [3, 1]),
                     helper.make_tensor("full", TensorProto.INT64, [2], [3, width])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", ONNX_OPSET)])
    model.ir_version = ONNX_IR_VERSION
    helper.set_model_props(model, _metadata().to_props())
    return model


def _looping_model() -> onnx.ModelProto:
    """The linear model plus a ``Loop`` of 10^15 iterations whose count reaches the output (times zero)."""
    model = linear_model(_bias(), weight_scale=0.1, metadata=_metadata())
    body = helper.make_graph(
        [helper.make_node("Identity", ["cond_in"], ["cond_out"]),
         helper.make_node("Add", ["count_in", "one"], ["count_out"])],
        "body",
        [helper.make_tensor_value_info("i", TensorProto.INT64, []),
         helper.make_tensor_value_info("cond_in", TensorProto.BOOL, []),
         helper.make_tensor_value_info("count_in", TensorProto.FLOAT, [])],
        [helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
         helper.make_tensor_value_info("count_out", TensorProto.FLOAT, [])],
        initializer=[helper.make_tensor("one", TensorProto.FLOAT, [], [1.0])],
    )
    graph = model.graph
    graph.initializer.extend([helper.make_tensor("trips", TensorProto.INT64, [], [10**15]),
                              helper.make_tensor("go", TensorProto.BOOL, [], [True]),
                              helper.make_tensor("zero", TensorProto.FLOAT, [], [0.0])])
    graph.node[-1].output[0] = "linear"
    graph.node.extend([helper.make_node("Loop", ["trips", "go", "zero"], ["count"], body=body),
                       helper.make_node("Mul", ["count", "zero"], ["nothing"]),
                       helper.make_node("Add", ["linear", "nothing"], [OUTPUT_NAME])])
    onnx.checker.check_model(model)
    return model


def _fixed_batch_model(batch: int) -> onnx.ModelProto:
    model = linear_model(_bias(), weight_scale=0.1, metadata=_metadata())
    model.graph.input[0].type.tensor_type.shape.dim[0].dim_value = batch
    model.graph.output[0].type.tensor_type.shape.dim[0].dim_value = batch
    return model


def write_hostile_files(folder: Path) -> Path:
    """Every file the catalogue names, in ``folder``; returns ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
    good = _metadata().to_props()
    onnx.save(linear_model(_bias(), weight_scale=0.1, metadata=_metadata()), str(folder / "model.onnx"))
    for name, (key, text, _) in METADATA_CASES.items():
        props = {**good, key: text} if text is not None else {k: v for k, v in good.items() if k != key}
        onnx.save(_with_props(props), str(folder / f"meta_{name}.onnx"))

    marked = _with_props({**good, "popcode.training": f'"{_NON_UTF8_MARK}"'}).SerializeToString()
    (folder / "non_utf8.onnx").write_bytes(marked.replace(_NON_UTF8_MARK.encode(), b"\xff\xfe" * 8))
    (folder / "junk.onnx").write_bytes(b"\x00garbage")
    (folder / "empty.onnx").write_bytes(b"")
    (folder / "truncated.onnx").write_bytes((folder / "model.onnx").read_bytes()[:200])
    wrong_input = linear_model(_bias(), metadata=_metadata())
    wrong_input.graph.input[0].name = "pixels"
    wrong_input.graph.node[0].input[0] = "pixels"
    onnx.save(wrong_input, str(folder / "wrong_input.onnx"))
    onnx.save(linear_model(_bias(), metadata=_metadata(), output_dim=LAYOUT.size - 1), str(folder / "wrong_width.onnx"))
    onnx.save(_runtime_failure_model(), str(folder / "run_fails.onnx"))
    onnx.save(_looping_model(), str(folder / "loops.onnx"))
    onnx.save(_fixed_batch_model(100_000), str(folder / "batch_huge.onnx"))
    single = ModelMetadata(representation=Representation.SINGLE_VARIABLE, code=LAYOUT, objects={7: OBJECT})
    onnx.save(linear_model(matrix_to_sixd(np.eye(3)).astype(np.float32), metadata=single),
              str(folder / "single_variable.onnx"))

    scene = np.random.default_rng(0).integers(0, 256, size=IMAGE_SHAPE, dtype=np.uint8)
    cv2.imwrite(str(folder / "scene.png"), scene)
    (folder / "text.png").write_text("not an image\n")
    (folder / "empty.png").write_bytes(b"")
    (folder / "truncated.png").write_bytes((folder / "scene.png").read_bytes()[:60])
    (folder / "huge.png").write_bytes(_png_header(100_000, 100_000) + b"\x00" * 64)
    (folder / "huge.jpg").write_bytes(_jpeg_header(60_000, 60_000) + b"\x00" * 64)
    (folder / "over_opencv_limit.png").write_bytes(_png_claiming(40_000, 30_000))  # 1.2e9 > 2^30 pixels

    depth_meta = ModelMetadata(representation=Representation.POPULATION_CODE, code=LAYOUT, objects={7: DEPTH_OBJECT})
    onnx.save(linear_model(_bias(), weight_scale=0.1, metadata=depth_meta), str(folder / "depth_model.onnx"))
    cv2.imwrite(str(folder / "depth.png"), np.full(IMAGE_SHAPE, DEPTH_MM, np.uint16))
    cv2.imwrite(str(folder / "depth_small.png"), np.full((60, 80), DEPTH_MM, np.uint16))
    cv2.imwrite(str(folder / "depth_colour.png"), np.full((*IMAGE_SHAPE, 3), 100, np.uint8))
    cv2.imwrite(str(folder / "depth_far.png"), np.full(IMAGE_SHAPE, 65535, np.uint16))
    # issue 50: cameras and depth
    depth_png = (folder / "depth.png").read_bytes()
    (folder / "depth_torn.png").write_bytes(depth_png[: len(depth_png) // 2])  # libpng: "Read Error"
    damaged = bytearray(depth_png)
    damaged[depth_png.index(b"IDAT") + 8] ^= 0xFF  # a byte of the pixel data: the chunk's CRC no longer holds
    (folder / "depth_damaged.png").write_bytes(bytes(damaged))
    cv2.imwrite(str(folder / "depth_rgba16.png"), np.full((*IMAGE_SHAPE, 4), DEPTH_MM, np.uint16))
    _write_split(folder / "split_unscaled", {"cam_K": parse_camera_matrix(GOOD_K_LIST).ravel().tolist()})
    other_camera = parse_camera_matrix([864.0, 864.0, 359.5, 269.5])  # a 720x540 camera's, not scene.png's
    _write_split(folder / "split_other_camera", {"cam_K": other_camera.ravel().tolist(), "depth_scale": 1.0})
    return folder


def _write_split(split: Path, camera: dict) -> None:
    """One scene of one image of object 7 (depth.png's depth beside scene.png) whose scene_camera.json entry is
    ``camera``."""
    scene = split / "000001"
    for kind, name in (("gray", "scene.png"), ("depth", "depth.png")):
        (scene / kind).mkdir(parents=True, exist_ok=True)
        (scene / kind / "000000.png").write_bytes((split.parent / name).read_bytes())
    (scene / "scene_camera.json").write_text(json.dumps({"0": camera}))
    (scene / "scene_gt.json").write_text(json.dumps({"0": [{"cam_R_m2c": np.eye(3).ravel().tolist(),
                                                            "cam_t_m2c": [0, 0, DEPTH_MM], "obj_id": 7}]}))
    (scene / "scene_gt_info.json").write_text(json.dumps({"0": [{"bbox_obj": [20, 20, 60, 50],
                                                                 "bbox_visib": [20, 20, 60, 50], "visib_fract": 1.0}]}))
