"""Enum names are their text wherever text is made of them: messages, file names, JSON metadata."""

import json

from popcode_runtime.geometry.symmetries import SymmetryClass
from popcode_runtime.model.metadata import Representation, RotationFrame


def test_members_print_and_serialise_as_their_value() -> None:
    for member in (Representation.POPULATION_CODE, RotationFrame.ALLOCENTRIC, SymmetryClass.CONTINUOUS):
        assert f"{member}" == str(member) == member.value
        assert f"{member:>20}" == f"{member.value:>20}"
        assert json.dumps({"k": member}) == json.dumps({"k": member.value})
        assert member == member.value and type(member)(member.value) is member


def test_values_list_every_member_in_order() -> None:
    assert Representation.values() == ("population_code", "one_hot", "single_variable", "multi_hypothesis")
    assert RotationFrame.values() == ("egocentric", "allocentric")
