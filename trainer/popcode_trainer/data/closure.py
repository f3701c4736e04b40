"""A set closed under composition: the group a declared symmetry set, or one with look-alike turns, generates."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

T = TypeVar("T")


def closure(start: Sequence[T], steps: Sequence[T], compose: Callable[[T, T], T],
            known: Callable[[T, list[T]], bool], limit: int) -> tuple[list[T], list[T], bool]:
    """``start`` and every product of its elements with ``steps`` (breadth first; a product is added unless
    ``known(product, elements)``): the elements, those the products added, and whether the set closed before it
    held more than ``limit``."""
    elements, added = list(start), []
    frontier = list(start)
    while frontier:
        grown = []
        for a in frontier:
            for b in steps:
                product = compose(a, b)
                if not known(product, elements):
                    elements.append(product)
                    added.append(product)
                    grown.append(product)
                    if len(elements) > limit:
                        return elements, added, False
        frontier = grown
    return elements, added, True
