"""Issue 50: what a crafted model's metadata can make the runtime do is bounded before the work it would size."""

from __future__ import annotations

import numpy as np
import pytest
from symmetry_cases import CASES

from popcode_runtime import CodeLayout, ModelMetadata, PopcodeError, symmetry_transforms
from popcode_runtime.base import limits
from popcode_runtime.geometry import symmetries
from popcode_runtime.model import metadata

LAYOUT = CodeLayout(n_axes=42, n_angles=12)


def test_metadata_over_the_limit_is_refused_before_any_of_it_is_parsed(monkeypatch: pytest.MonkeyPatch) -> None:
    good = ModelMetadata(representation="population_code", code=LAYOUT, objects={1: CASES["two_fold"]}).to_props()
    props = {**good, "popcode.training": " " * limits.MAX_METADATA_CHARS}

    def parsed(*args: object) -> None:
        raise AssertionError("metadata was parsed before its size was checked")

    monkeypatch.setattr(metadata, "parse_json", parsed)
    with pytest.raises(PopcodeError, match=r"the model's metadata holds [\d,]+ characters, more than the limit of "
                                           r"16,777,216: export fewer objects per model"):
        ModelMetadata.from_props(props)


@pytest.mark.parametrize(("info", "expect"), [
    ({"symmetries_discrete": [object()] * (limits.MAX_DISCRETE_SYMMETRIES + 1)},
     "symmetries_discrete lists 1001 symmetries; at most 1000 are allowed"),
    ({"symmetries_continuous": [object()] * (limits.MAX_CONTINUOUS_SYMMETRIES + 1)},
     "symmetries_continuous lists 4 symmetries; at most 3 are allowed"),
], ids=["discrete", "continuous"])
def test_symmetries_are_counted_before_any_is_read(info: dict, expect: str) -> None:
    with pytest.raises(PopcodeError, match=expect):
        symmetry_transforms(info)


@pytest.mark.parametrize(("info", "expect"), [
    ({"symmetries_discrete": [["1", 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]},
     r"symmetries_discrete\[0\] is not a list of numbers: got \['1', 0"),
    ({"symmetries_discrete": [[-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, True, 0, 0, 0, 0, 1]]}, "is not a list of numbers"),
    ({"symmetries_continuous": [{"axis": [0, 0, 1], "offset": [True, 0, 0]}]},
     r"symmetries_continuous\[0\] offset is not a list of numbers"),
    ({"symmetries_continuous": [{"axis": [0, 0, 10**400]}]}, r"symmetries_continuous\[0\] axis contains NaN or inf"),
], ids=["text", "true", "offset-true", "axis-overflows"])
def test_symmetry_numbers_are_numbers(info: dict, expect: str) -> None:
    with pytest.raises(PopcodeError, match=expect):
        symmetry_transforms(info)


def test_loading_reads_symmetries_without_expanding_them(monkeypatch: pytest.MonkeyPatch) -> None:
    """A continuous symmetry is 315 transforms per discrete one in the metrics; a model's check needs none of them,
    so a declaration at the limits loads in the time it takes to read it."""
    def expanded(*args: object) -> None:
        raise AssertionError("a continuous symmetry was expanded to check a model")

    monkeypatch.setattr(symmetries, "axis_angle_to_matrix", expanded)
    turns = [np.diag([-1.0, 1.0, -1.0, 1.0]).ravel().tolist()]  # the flip of CASES["continuous_flip"]
    axes = [{"axis": [0, 0, 1]}] * limits.MAX_CONTINUOUS_SYMMETRIES
    layout = CodeLayout(n_axes=42, n_angles=12, axis_only=True, symmetry_axis=(0.0, 0.0, 1.0))
    loaded = ModelMetadata.from_props(ModelMetadata(
        representation="population_code", code=layout,
        objects={1: {**CASES["none"], "symmetries_discrete": turns, "symmetries_continuous": axes}}).to_props())
    assert len(loaded.objects[1]["symmetries_continuous"]) == limits.MAX_CONTINUOUS_SYMMETRIES
