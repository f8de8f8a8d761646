"""Cross-checks of SO3 / SE3 against independent libraries (kornia, pytorch_kinematics, roma).

Every comparison is in float64 on seeded random inputs. Conventions that matter:

* kornia's ``Se3`` tangent is ``[v, ω]`` (translation first), like ours, and its
  ``Se3.exp(xi).t`` is ``V(ω) v`` with ``V = J_l(ω)``, so the matrices must agree entry by entry.
* Rotations are compared away from π (angle < π − 0.1): at π the sign of a rotation vector is
  ambiguous and each library may pick a different one.
* pytorch_kinematics (a pytorch3d port) clamps θ² at 1e-4 in ``so3_exp_map`` and linearly
  extrapolates ``acos`` for |cos θ| > 1 − 1e-4 in ``so3_log_map``, so it is only exact for
  0.0142 < θ < π − 0.0142; its inputs here stay in [0.05, π − 0.1].
"""

import math

import pytorch_kinematics as pk  # a runtime dependency of posediff
import roma  # a dev dependency (benchmarks peer)
import torch
from kornia.geometry.liegroup import Se3, So3  # a runtime dependency of posediff
from torch.testing import assert_close

from posediff.lie import SE3, SO3
from posediff.testing import tangents_at_angles

F64 = torch.float64
TOL = {"atol": 1e-10, "rtol": 0.0}
SMALL = [0.0, 1e-12, 1e-8, 1e-6, 1e-4, 1e-2]


def _angles(n: int, seed: int, low: float = 0.05, high: float = math.pi - 0.1) -> list[float]:
    u = torch.rand(n, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return (low + (high - low) * u).tolist()


def _rotvecs(angles: list[float], seed: int) -> torch.Tensor:
    return tangents_at_angles(SO3(), angles, seed=seed, dtype=F64)


def _se3_tangents(angles: list[float], seed: int) -> torch.Tensor:
    return tangents_at_angles(SE3(), angles, seed=seed, dtype=F64, trans_scale=2.0)


# ------------------------------------------------------------------------------ kornia
def test_kornia_so3_exp() -> None:
    v = _rotvecs(SMALL + _angles(64, seed=1), seed=2)
    expected = So3.exp(v).matrix().detach()
    assert_close(SO3().exp(v), expected, **TOL)


def test_kornia_so3_log() -> None:
    v = _rotvecs(SMALL + _angles(64, seed=3), seed=4)
    R = SO3().exp(v)
    expected = So3.from_matrix(R).log().detach()
    assert_close(SO3().log(R), expected, **TOL)
    # and on Haar-random rotations (kept below π − 0.1), built by kornia from Gaussian quaternions
    q = torch.randn(256, 4, generator=torch.Generator().manual_seed(5), dtype=F64)
    R2 = So3.from_wxyz(q / q.norm(dim=-1, keepdim=True)).matrix().detach()
    keep = So3.from_matrix(R2).log().detach().norm(dim=-1) < math.pi - 0.1
    assert int(keep.sum()) > 100
    R2 = R2[keep]
    assert_close(SO3().log(R2), So3.from_matrix(R2).log().detach(), **TOL)


def test_kornia_se3_exp() -> None:
    xi = _se3_tangents(SMALL + _angles(64, seed=6), seed=7)
    expected = Se3.exp(xi).matrix().detach()
    assert_close(SE3().exp(xi), expected, **TOL)


def test_kornia_se3_log() -> None:
    xi = _se3_tangents(SMALL + _angles(64, seed=8), seed=9)
    G = SE3().exp(xi)
    expected = Se3.from_matrix(G).log().detach()
    assert_close(SE3().log(G), expected, **TOL)
    # both recover the tangent (kornia's log is also principal below π)
    assert_close(SE3().log(G), xi, **TOL)


# ------------------------------------------------------------------------------ pytorch_kinematics
def test_pytorch_kinematics_so3_exp() -> None:
    v = _rotvecs(_angles(64, seed=10), seed=11)
    assert_close(SO3().exp(v), pk.so3_exp_map(v), **TOL)


def test_pytorch_kinematics_so3_log() -> None:
    v = _rotvecs(_angles(64, seed=12), seed=13)
    R = SO3().exp(v)
    assert_close(SO3().log(R), pk.so3_log_map(R), **TOL)


def test_near_pi_where_pytorch_kinematics_log_breaks() -> None:
    """At θ = π − 1e-3, inside the 0.014 rad band where pytorch_kinematics' log is wrong
    (measured: its error is ~2.4 rad there, because it clamps sin θ at 1e-4 and extrapolates
    acos linearly), ours still round-trips to round-off. Only our side is asserted; roma and
    kornia (quaternion-based, exact there) serve as the independent oracle."""
    v = _rotvecs([math.pi - 1e-3] * 16, seed=14)
    R = SO3().exp(v)
    ours = SO3().log(R)
    assert_close(ours, v, **TOL)
    assert_close(SO3().exp(ours), R, atol=1e-12, rtol=0.0)
    assert_close(ours, roma.rotmat_to_rotvec(R), **TOL)
    assert_close(ours, So3.from_matrix(R).log().detach(), **TOL)
    # pk's exp is fine there (only its log is not): our matrices match it
    assert_close(R, pk.so3_exp_map(v), **TOL)


# ------------------------------------------------------------------------------ roma
def test_roma_so3_exp() -> None:
    v = _rotvecs(SMALL + _angles(64, seed=15), seed=16)
    assert_close(SO3().exp(v), roma.rotvec_to_rotmat(v), **TOL)


def test_roma_so3_log() -> None:
    v = _rotvecs(SMALL + _angles(64, seed=17), seed=18)
    R = SO3().exp(v)
    assert_close(SO3().log(R), roma.rotmat_to_rotvec(R), **TOL)
    # Haar-random rotations (angles kept below π − 0.1, where the sign of the vector is defined)
    R2 = SO3().sample_uniform((256,), generator=torch.Generator().manual_seed(19), dtype=F64)
    ref = roma.rotmat_to_rotvec(R2)
    keep = ref.norm(dim=-1) < math.pi - 0.1
    assert int(keep.sum()) > 100
    assert_close(SO3().log(R2[keep]), ref[keep], **TOL)
    assert_close(SO3().exp(ref[keep]), R2[keep], atol=1e-12, rtol=0.0)
