# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 01 — Lie groups in posediff
#
# What this shows:
# 1. Elements are matrices, tangents are `[ρ, φ]`, perturbations act on the right.
# 2. `exp`/`log` round trips, including rotations of exactly π.
# 3. **R3SO3 vs SE3 on a coupled motion**: the same tangent vector gives a straight line in
#    R3SO3 and a screw in SE3; and the closed-form score `−J_r⁻ᵀ(z) z/σ²` equals the surrogate
#    `−z/σ²` for R3SO3 (paper Eq. 10) but not for SE3 (Eq. 13).

# %%
import math
import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import torch

from posediff.lie import R3SO3, SE3, SO3, get_group

FAST = os.environ.get("POSEDIFF_FAST", "1") == "1"
OUT = Path(os.environ.get("POSEDIFF_NOTEBOOK_OUT", "outputs/notebooks"))
torch.manual_seed(0)
torch.set_default_dtype(torch.float64)

# %% [markdown]
# ## 1. Elements, tangents, registry

# %%
se3 = get_group("se3")
xi = torch.tensor([0.5, -0.2, 0.1, 0.0, 0.0, math.pi / 3])  # [ρ, φ]
g = se3.exp(xi)
print("SE3 element (4×4):\n", g)
print("log(exp(ξ)) =", se3.log(g))
print("registered groups:", sorted(SE3.registry))

# %% [markdown]
# ## 2. Round trips at the hard angles

# %%
so3 = SO3()
for angle in [0.0, 1e-8, 1.0, math.pi - 1e-7, math.pi]:
    phi = torch.tensor([0.0, angle, 0.0])
    R = so3.exp(phi)
    err_back = (so3.exp(so3.log(R)) - R).abs().max().item()
    print(f"θ = {angle:.10f}: |exp(log R) − R| = {err_back:.1e}, |log R| = {so3.log(R).norm():.10f}")

R_pi = torch.diag(torch.tensor([1.0, -1.0, -1.0]))  # a rotation of exactly π about x
print("log of diag(1, −1, −1):", so3.log(R_pi))

# %% [markdown]
# ## 3. R3SO3 vs SE3 on a coupled motion
#
# One tangent vector, a unit translation along x with a quarter turn about z, followed from
# `t = 0` to `1`: `Exp(t ξ)`.

# %%
xi = torch.tensor([1.0, 0.0, 0.0, 0.0, 0.0, math.pi / 2])
ts = torch.linspace(0, 1, 11 if FAST else 101)
paths = {}
for group in (R3SO3(), SE3()):
    poses = group.exp(ts[:, None] * xi)
    paths[group.name] = poses[:, :3, 3]
    end = poses[-1, :3, 3]
    print(f"{group.name:6s} end translation = {end.numpy().round(4)}")

fig, ax = plt.subplots(figsize=(4, 4))
for name, p in paths.items():
    ax.plot(p[:, 0], p[:, 1], marker="o", ms=3, label=name)
ax.set_xlabel("x")
ax.set_ylabel("y")
ax.set_aspect("equal")
ax.set_title("Exp(t ξ), ξ = [1,0,0 | 0,0,π/2]")
ax.legend()
OUT.mkdir(parents=True, exist_ok=True)
fig.savefig(OUT / "01_r3so3_vs_se3.png", dpi=120, bbox_inches="tight")
print("figure:", OUT / "01_r3so3_vs_se3.png")

# %% [markdown]
# The closed-form score direction `J_r⁻ᵀ(z) z` against the surrogate `z`:

# %%
z = torch.tensor([0.3, -0.2, 0.5, 0.4, 0.1, -0.7])
for group in (R3SO3(), SE3()):
    closed = group.jac_right_inv(z).mT @ z
    print(f"{group.name:6s} |J_r⁻ᵀ(z) z − z| = {(closed - z).norm():.3e}")
    if isinstance(group, R3SO3):
        assert torch.allclose(closed, z, atol=1e-12)
    else:
        assert (closed - z).norm() > 1e-2
