"""Decomposable triangulated structure as the paper's integer string (eq. 15).

A structure over ``n`` vertices is ``n - 2`` triangles ``(A_t, B_t, C_t)``. Triangle 0 holds
three distinct vertices; every later triangle adds one *new* vertex ``A_t`` (the paper puts
the new integer first) joined to two vertices ``B_t, C_t`` already in the graph. Read in
reverse, the list is the elimination order: ``A_t`` is the free vertex of its clique.

Ambiguity resolved: the paper only asks that ``B_t, C_t`` be "selected from the previous
triangles". For the graph to be a *decomposable triangulated* graph (Amit & Kong) and for
``P(A|B,C)`` to chain into a proper joint density with consistent cliques, ``(B_t, C_t)``
must be an **edge** of an earlier triangle. We enforce that stricter, mathematically sound
reading everywhere (initialisation, repair, validation).

The joint density factorises as (eq. 5, 15, 19)::

    P(X) = P(X_A0, X_B0, X_C0) * prod_{t>0} P(X_At | X_Bt, X_Ct)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np


class StructureError(ValueError):
    """An integer string that is not a decomposable triangulated structure."""


def _edge(a: int, b: int) -> tuple[int, int]:
    return (a, b) if a < b else (b, a)


@dataclass(frozen=True)
class Structure:
    """Validated triangulated structure; ``triangles[t] = (A_t, B_t, C_t)``."""

    triangles: tuple[tuple[int, int, int], ...]
    n_vertices: int

    def __post_init__(self) -> None:
        tri = tuple(tuple(int(v) for v in t) for t in self.triangles)
        object.__setattr__(self, "triangles", tri)
        problem = structure_problem(np.asarray(tri, dtype=np.int64).reshape(-1, 3), self.n_vertices)
        if problem:
            raise StructureError(problem)

    # -- construction -------------------------------------------------------------------
    @classmethod
    def from_string(cls, genes: Sequence[int] | np.ndarray, n_vertices: int | None = None) -> "Structure":
        """From the flat integer string ``(A0 B0 C0 A1 B1 C1 ...)`` of eq. 15."""
        g = np.asarray(genes, dtype=np.int64).ravel()
        if g.size % 3:
            raise StructureError(f"string length {g.size} is not a multiple of 3")
        n = int(n_vertices if n_vertices is not None else g.size // 3 + 2)
        return cls(tuple(map(tuple, g.reshape(-1, 3).tolist())), n)

    @classmethod
    def from_names(cls, triangles: Iterable[Sequence[str]], labels: Sequence[str]) -> "Structure":
        idx = {n: i for i, n in enumerate(labels)}
        try:
            tri = tuple(tuple(idx[v] for v in t) for t in triangles)
        except KeyError as e:
            raise StructureError(f"structure names unknown label {e.args[0]!r}") from None
        return cls(tri, len(labels))

    # -- views --------------------------------------------------------------------------
    @property
    def array(self) -> np.ndarray:
        return np.asarray(self.triangles, dtype=np.int64)

    def to_string(self) -> list[int]:
        return [v for t in self.triangles for v in t]

    @property
    def n_triangles(self) -> int:
        return len(self.triangles)

    def edges(self) -> set[tuple[int, int]]:
        out: set[tuple[int, int]] = set()
        for a, b, c in self.triangles:
            out |= {_edge(a, b), _edge(a, c), _edge(b, c)}
        return out

    def elimination_order(self) -> list[int]:
        """Vertices in elimination order (each free in what remains): reverse of insertion."""
        order = [t[0] for t in reversed(self.triangles[1:])]
        return order + list(self.triangles[0])

    def names(self, labels: Sequence[str]) -> list[list[str]]:
        return [[labels[v] for v in t] for t in self.triangles]


def structure_problem(tri: np.ndarray, n_vertices: int) -> str:
    """Why ``tri`` (T x 3) is not a valid structure over ``n_vertices``; '' if it is."""
    if n_vertices < 3:
        return f"need at least 3 vertices, got {n_vertices}"
    if tri.shape != (n_vertices - 2, 3):
        return f"{n_vertices} vertices need {n_vertices - 2} triangles, got {tri.shape[0]}"
    if tri.min() < 0 or tri.max() >= n_vertices:
        return f"vertex index out of range 0..{n_vertices - 1}"
    a, b, c = (int(v) for v in tri[0])
    if len({a, b, c}) != 3:
        return f"first triangle {tri[0].tolist()} repeats a vertex"
    used = {a, b, c}
    edges = {_edge(a, b), _edge(a, c), _edge(b, c)}
    for t in range(1, tri.shape[0]):
        a, b, c = (int(v) for v in tri[t])
        if a in used:
            return f"triangle {t}: new vertex {a} is already in the graph"
        if b == c or b not in used or c not in used:
            return f"triangle {t}: parents {b},{c} must be two distinct vertices already in the graph"
        if _edge(b, c) not in edges:
            return f"triangle {t}: parents ({b},{c}) are not an edge of an earlier triangle"
        used.add(a)
        edges |= {_edge(a, b), _edge(a, c)}
    return ""


def is_valid(genes: np.ndarray, n_vertices: int) -> bool:
    g = np.asarray(genes, dtype=np.int64).reshape(-1, 3)
    return not structure_problem(g, n_vertices)


# The hand-given structure for the paper's 14 body points (its Fig. 2: 14 points, 12
# triangles): torso first, then head, arms and legs hanging off torso edges.
BODY14_GIVEN = (
    ("lshoulder", "rshoulder", "neck"),
    ("head", "neck", "lshoulder"),
    ("lhip", "lshoulder", "rshoulder"),
    ("rhip", "lhip", "rshoulder"),
    ("lelbow", "lshoulder", "lhip"),
    ("lwrist", "lelbow", "lshoulder"),
    ("relbow", "rshoulder", "rhip"),
    ("rwrist", "relbow", "rshoulder"),
    ("lknee", "lhip", "rhip"),
    ("lankle", "lknee", "lhip"),
    ("rknee", "rhip", "lhip"),
    ("rankle", "rknee", "rhip"),
)
