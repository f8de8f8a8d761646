"""The ``[[R, t], [0, 1]]`` matrix layout shared by R3SO3 and SE3 (and, in 2-D, SE2)."""

import torch
from torch import Tensor

from .so3 import Mat3, Vec3, project_rotation, rotation_error, skew, stack_entries, uniform_rotation, unskew


def make_pose(R: Tensor, t: Tensor) -> Tensor:
    """``R (*b, k, k)``, ``t (*b, k)`` → ``(*b, k+1, k+1)``; broadcasts R against t."""
    k = R.shape[-1]
    batch = torch.broadcast_shapes(R.shape[:-2], t.shape[:-1])
    top = torch.cat([R.expand(*batch, k, k), t.expand(*batch, k).unsqueeze(-1)], dim=-1)
    bottom = torch.zeros(k + 1, dtype=R.dtype, device=R.device)
    bottom[k] = 1.0
    return torch.cat([top, bottom.expand(*batch, 1, k + 1)], dim=-2)


def split_pose(g: Tensor) -> tuple[Tensor, Tensor]:
    """``(*b, k+1, k+1)`` → ``R (*b, k, k)``, ``t (*b, k)`` (views)."""
    k = g.shape[-1] - 1
    return g[..., :k, :k], g[..., :k, k]


def pose_error(g: Tensor) -> Tensor:
    """Max violation of a valid ``[[R, t], [0, 1]]`` with R a rotation, ``(*b,)``."""
    k = g.shape[-1] - 1
    expected = torch.zeros(k + 1, dtype=g.dtype, device=g.device)
    expected[k] = 1.0
    row = (g[..., k, :] - expected).abs().amax(-1)
    return torch.maximum(rotation_error(g[..., :k, :k]), row)


def project_pose(m: Tensor) -> Tensor:
    R, t = split_pose(m)
    return make_pose(project_rotation(R) if R.shape[-1] == 3 else _project_rotation2(R), t)


def _project_rotation2(m: Tensor) -> Tensor:
    # nearest 2-D rotation: the angle of (m00 + m11, m10 - m01)
    ang = torch.atan2(m[..., 1, 0] - m[..., 0, 1], m[..., 0, 0] + m[..., 1, 1])
    c, s = torch.cos(ang), torch.sin(ang)
    return torch.stack([c, -s, s, c], dim=-1).unflatten(-1, (2, 2))


def uniform_pose(
    shape: tuple[int, ...],
    generator: torch.Generator | None,
    device: torch.device,
    dtype: torch.dtype,
    bound: float,
) -> Tensor:
    """Haar rotation and translation uniform in ``[-bound, bound]³``."""
    R = uniform_rotation(shape, generator, device, dtype)
    u = torch.rand(*shape, 3, generator=generator, device=device, dtype=dtype)
    return make_pose(R, (2.0 * u - 1.0) * bound)


def block_matrix(rows: list[list[Tensor]]) -> Tensor:
    """Assemble ``(*b, ., .)`` blocks (broadcast against each other) into one matrix."""
    batch = torch.broadcast_shapes(*(blk.shape[:-2] for row in rows for blk in row))
    return torch.cat(
        [torch.cat([blk.expand(*batch, *blk.shape[-2:]) for blk in row], dim=-1) for row in rows], dim=-2
    )


def pose_act(g: Tensor, p: Tensor) -> Tensor:
    """``R p + t`` for points ``(*b, k)``."""
    R, t = split_pose(g)
    return (R @ p.unsqueeze(-1)).squeeze(-1) + t


def pose_hat(xi: Tensor) -> Tensor:
    """``[ρ, φ]`` → ``[[φ×, ρ], [0, 0]]`` (4×4)."""
    top = torch.cat([skew(xi[..., 3:]), xi[..., :3].unsqueeze(-1)], dim=-1)
    return torch.cat([top, torch.zeros_like(top[..., :1, :])], dim=-2)


def pose_vee(X: Tensor) -> Tensor:
    """``[[φ×, ρ], [0, 0]]`` → ``[ρ, φ]``."""
    return torch.cat([X[..., :3, 3], unskew(X[..., :3, :3])], dim=-1)


def pose_from_entries(R: Mat3, t: Vec3) -> Tensor:
    """A ``(*b, 4, 4)`` pose from the 9 rotation and 3 translation entries, in one write."""
    o = torch.zeros_like(t[0])
    i = torch.ones_like(t[0])
    return stack_entries([*R[0:3], t[0], *R[3:6], t[1], *R[6:9], t[2], o, o, o, i], 4, 4)


def pose_entries(g: Tensor) -> tuple[Mat3, Vec3]:
    """The 9 rotation and 3 translation entries of a ``(*b, 4, 4)`` pose."""
    e = g.flatten(-2).unbind(-1)
    return (e[0], e[1], e[2], e[4], e[5], e[6], e[8], e[9], e[10]), (e[3], e[7], e[11])


def pose_inverse(g: Tensor) -> Tensor:
    """``[[R, t], [0, 1]]⁻¹ = [[Rᵀ, −Rᵀt], [0, 1]]`` (SE(2) and SE(3))."""
    R, t = split_pose(g)
    Rt = R.mT
    return make_pose(Rt, -(Rt @ t.unsqueeze(-1)).squeeze(-1))
