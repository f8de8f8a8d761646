"""The symmetries of one object as a value: :class:`SymmetrySet`, from a SYMSOL shape or a BOP
``models_info`` entry, and the one "smallest angle over the symmetries" every metric uses.

Conventions (``docs/conventions.md``): symmetries act on the **right**, in the model frame — the
poses ``[R | t]`` and ``[R·R_S | t + R·t_S]`` look the same for every member ``(R_S, t_S)``. A set holds

* finite members ``(R_k, t_k)``, the identity first (SYMSOL's exact polyhedral groups; BOP's
  ``symmetries_discrete``, 4×4 row-major, mm);
* continuous axes ``(a, o)``: every rotation about the axis ``a`` through the point ``o``
  (SYMSOL's cone / cylinder about z; BOP's ``symmetries_continuous``), discretised on demand.

:meth:`SymmetrySet.transforms` is the BOP discretisation (as the toolkit's
``misc.get_symmetry_transformations``): ``n = ceil(π / max_sym_disc_step)`` turns
``R_j = Rot(a, 2πj/n)``, ``t_j = o − R_j·o`` (j = 0 … n − 1), each composed with every finite member,
``(R_j R_k, R_j t_k + t_j)``. :meth:`SymmetrySet.rotations` gives the rotations alone (SYMSOL's cone /
cylinder on a ``step_deg`` grid, as the authors' evaluation). :meth:`SymmetrySet.min_angle_deg` is
the smallest geodesic angle from an estimate to the equivalents of a ground truth: exact (closed form)
for the SYMSOL shapes, over the discretised set otherwise (at most half a step above the exact one).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

from .groups import SHAPES, is_continuous, min_angle_to_equivalents, symmetry_group

_CHUNK = 1 << 22  # (rotation, member) trace entries per block of min_angle_deg (~32 MB of float64)


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """``Rot(axis, angle)`` (float64), through the group's own exponential map."""
    from ..lie.so3 import exp_so3

    a = np.asarray(axis, dtype=np.float64)
    phi = torch.from_numpy(a / np.linalg.norm(a) * angle)
    return exp_so3(phi).numpy()


@dataclass(frozen=True, eq=False)
class SymmetrySet:
    """The symmetries of one object (module docstring). Build it with :meth:`from_shape`,
    :meth:`from_models_info` or :meth:`identity`; it is immutable and cheap to share."""

    #: finite members, identity first: rotations ``(K, 3, 3)`` and translations ``(K, 3)`` (model units)
    rotations_finite: np.ndarray
    translations_finite: np.ndarray
    #: continuous symmetries: ``(axis (3,), offset (3,))`` each
    axes: tuple[tuple[np.ndarray, np.ndarray], ...] = ()
    #: what it was made from (a SYMSOL shape, ``obj_000001``, …), for messages and tables
    name: str = ""
    #: the SYMSOL shape, when it is one: distances use the exact continuous groups in closed form
    shape: str | None = None
    _cache: dict[Any, Any] = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self) -> None:
        R = np.asarray(self.rotations_finite, dtype=np.float64).reshape(-1, 3, 3)
        t = np.asarray(self.translations_finite, dtype=np.float64).reshape(-1, 3)
        if len(R) == 0 or len(R) != len(t):
            raise ValueError(f"symmetry set {self.name!r}: {len(R)} rotations but {len(t)} translations")
        object.__setattr__(self, "rotations_finite", R)
        object.__setattr__(self, "translations_finite", t)

    # ------------------------------------------------------------------------------ construction
    @classmethod
    def identity(cls, name: str = "no symmetry") -> SymmetrySet:
        return cls(np.eye(3)[None], np.zeros((1, 3)), name=name)

    @classmethod
    @functools.lru_cache(maxsize=16)
    def from_shape(cls, shape: str) -> SymmetrySet:
        """The exact group of a SYMSOL shape (:mod:`posediff.symmetry.groups`): the polyhedra's finite
        groups; the cone's rotations about z; the cylinder's about z and the flip Rx(π)."""
        if shape not in SHAPES:
            raise ValueError(f"unknown SYMSOL shape {shape!r}; expected one of {SHAPES}")
        z = (np.array([0.0, 0.0, 1.0]), np.zeros(3))
        if shape == "cone":
            return cls(np.eye(3)[None], np.zeros((1, 3)), (z,), name=shape, shape=shape)
        if shape == "cyl":
            R = np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0])])
            return cls(R, np.zeros((2, 3)), (z,), name=shape, shape=shape)
        R = symmetry_group(shape).numpy()
        return cls(R, np.zeros((len(R), 3)), name=shape, shape=shape)

    @classmethod
    def from_models_info(cls, entry: Mapping[str, Any], name: str = "") -> SymmetrySet:
        """The symmetries of a BOP ``models_info`` entry: the identity, then each of
        ``symmetries_discrete`` (4×4 row-major), and the axes of ``symmetries_continuous``
        (``axis``, ``offset``, default the origin)."""
        R, t = [np.eye(3)], [np.zeros(3)]
        for k, sym in enumerate(entry.get("symmetries_discrete", [])):
            m = np.asarray(sym, dtype=np.float64)
            if m.size != 16:
                raise ValueError(
                    f"{name or 'models_info'}: symmetries_discrete[{k}] has {m.size} numbers, not 16 (a row-major 4×4)"
                )
            m = m.reshape(4, 4)
            R.append(m[:3, :3])
            t.append(m[:3, 3])
        axes = []
        for k, sym in enumerate(entry.get("symmetries_continuous", [])):
            axis = np.asarray(sym["axis"], dtype=np.float64).reshape(3)
            if not np.linalg.norm(axis) > 0:
                raise ValueError(f"{name or 'models_info'}: symmetries_continuous[{k}] has a zero axis")
            axes.append((axis, np.asarray(sym.get("offset", [0.0, 0.0, 0.0]), dtype=np.float64).reshape(3)))
        return cls(np.stack(R), np.stack(t), tuple(axes), name=name)

    @classmethod
    def from_transforms(cls, R: Any, t: Any = None, name: str = "") -> SymmetrySet:
        """A finite set given as its members ``R (S, 3, 3)`` (and ``t (S, 3)``, default zeros)."""
        R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
        t = np.zeros((len(R), 3)) if t is None else np.asarray(t, dtype=np.float64).reshape(-1, 3)
        return cls(R, t, name=name)

    # ------------------------------------------------------------------------------ queries
    @property
    def is_continuous(self) -> bool:
        return bool(self.axes)

    @property
    def num_modes(self) -> int | None:
        """How many distinct equivalent poses a pose has (None: infinitely many)."""
        return None if self.is_continuous else len(self.rotations_finite)

    def transforms(self, max_sym_disc_step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """``(R (S, 3, 3), t (S, 3))``: every member, the continuous axes discretised as BOP does
        (module docstring); a finite set as it is."""
        if not max_sym_disc_step > 0:
            raise ValueError(f"max_sym_disc_step must be > 0, got {max_sym_disc_step}")
        key = ("transforms", float(max_sym_disc_step))
        if key not in self._cache:
            if not self.axes:
                out = (self.rotations_finite, self.translations_finite)
            else:
                n = int(math.ceil(math.pi / max_sym_disc_step))
                turns = []
                for axis, offset in self.axes:
                    for j in range(n):
                        Rj = _axis_rotation(axis, 2.0 * math.pi * j / n)
                        turns.append((Rj, offset - Rj @ offset))
                Rs = [Rc @ Rd for Rd in self.rotations_finite for Rc, _ in turns]
                ts = [Rc @ td + tc for td in self.translations_finite for Rc, tc in turns]
                out = (np.stack(Rs), np.stack(ts))
            for a in out:
                a.setflags(write=False)
            self._cache[key] = out
        return self._cache[key]

    def rotations(self, *, step_deg: float = 1.0, max_sym_disc_step: float = 0.01) -> np.ndarray:
        """``(S, 3, 3)`` rotations of the members: a SYMSOL shape's group (the cone / cylinder every
        ``step_deg``, identity first, :func:`~posediff.symmetry.symmetry_group`), else those of
        :meth:`transforms`."""
        if self.shape is not None:
            return symmetry_group(self.shape, step_deg=step_deg).numpy()
        return self.transforms(max_sym_disc_step)[0]

    def min_angle_deg(self, R_est: Any, R_gt: Any, *, max_sym_disc_step: float = 0.01) -> Any:
        """The smallest geodesic angle (degrees) from each estimate to the equivalents
        ``{R_gt·R_S}``. Torch in → torch out (``R_est (…, N, 3, 3)`` with ``R_gt (…, 3, 3)``, or
        broadcastable, as :func:`~posediff.symmetry.min_angle_to_equivalents`; exact for SYMSOL
        shapes); numpy in → numpy ``(N,)`` for ``R_est``, ``R_gt (N, 3, 3)`` (:func:`min_angle_deg`)."""
        if isinstance(R_est, Tensor) or isinstance(R_gt, Tensor):
            R_est, R_gt = torch.as_tensor(R_est), torch.as_tensor(R_gt)
            if self.shape is not None:
                return torch.rad2deg(min_angle_to_equivalents(self.shape, R_est, R_gt))
            G = torch.from_numpy(np.array(self.rotations(max_sym_disc_step=max_sym_disc_step))).to(
                R_est
            )  # a copy: cached arrays are read-only
            if R_est.dim() == R_gt.dim() + 1:
                R_gt = R_gt.unsqueeze(-3)
            M = R_gt.mT @ R_est  # angle(R_gt S, R_est) = angle(Sᵀ M); tr(Sᵀ M) = Σ S ⊙ M
            tr = torch.einsum("...ij,sij->...s", M, G).amax(-1)
            return torch.rad2deg(torch.arccos(((tr - 1.0) / 2.0).clamp(-1.0, 1.0)))
        if self.shape is not None and is_continuous(self.shape):  # exact, through the torch path
            Re, Rg = (
                torch.from_numpy(np.asarray(a, dtype=np.float64).reshape(-1, 3, 3)) for a in (R_est, R_gt)
            )
            return torch.rad2deg(min_angle_to_equivalents(self.shape, Re, Rg)).numpy()
        return min_angle_deg(R_est, R_gt, self.rotations(max_sym_disc_step=max_sym_disc_step))

    def __len__(self) -> int:
        return len(self.rotations_finite)

    def __repr__(self) -> str:
        kind = f"{len(self.axes)} continuous axes, " if self.axes else ""
        return f"SymmetrySet({self.name or 'unnamed'}: {kind}{len(self)} finite members)"


def min_angle_deg(R_est: Any, R_gt: Any, R_S: Any) -> np.ndarray:
    """``min_S ∠(R_est, R_gt·R_S)`` in degrees, ``(N,)``, for ``R_est``, ``R_gt (N, 3, 3)`` (or
    ``(3, 3)``) and members ``R_S (S, 3, 3)``: ``tr(R_estᵀ R_gt R_S) = Σ (R_gtᵀ R_est) ⊙ R_S``, the
    largest over S, in blocks of bounded memory (float64)."""
    Re = np.asarray(R_est, dtype=np.float64).reshape(-1, 3, 3)
    Rg = np.asarray(R_gt, dtype=np.float64).reshape(-1, 3, 3)
    RS = np.asarray(R_S, dtype=np.float64).reshape(-1, 3, 3)
    if len(Re) != len(Rg):
        raise ValueError(f"R_est has {len(Re)} rotations, R_gt {len(Rg)}")
    M = np.einsum("nji,njk->nik", Rg, Re)
    out = np.empty(len(Re))
    step = max(1, _CHUNK // max(1, len(RS)))
    for lo in range(0, len(Re), step):
        tr = np.einsum("nij,sij->ns", M[lo : lo + step], RS).max(axis=1)
        out[lo : lo + step] = np.degrees(np.arccos(np.clip((tr - 1.0) / 2.0, -1.0, 1.0)))
    return out


def as_symmetry_set(symmetries: SymmetrySet | str | Sequence[Any] | None, name: str = "") -> SymmetrySet:
    """A :class:`SymmetrySet` from what metrics accept: a set; a SYMSOL shape name; ``None`` (no
    symmetry); a ``(R_S, t_S)`` pair; or rotations ``(S, 3, 3)``."""
    if isinstance(symmetries, SymmetrySet):
        return symmetries
    if symmetries is None:
        return SymmetrySet.identity()
    if isinstance(symmetries, str):
        return SymmetrySet.from_shape(symmetries)
    if isinstance(symmetries, tuple) and len(symmetries) == 2:
        return SymmetrySet.from_transforms(symmetries[0], symmetries[1], name=name)
    return SymmetrySet.from_transforms(symmetries, name=name)


__all__ = ["SymmetrySet", "as_symmetry_set", "min_angle_deg"]
