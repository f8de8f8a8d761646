# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 02 — Diffusion on SO(3), proven on a toy
#
# What this shows:
# 1. **The forward process**: a rotation noised with the concentrated Gaussian `R·Exp(z)`,
#    `z ~ N(0, σ²I)`, at a few σ; and how its angle law compares with the isotropic Gaussian
#    `IG_SO(3)` at σ = 0.2 (the same) and σ = 1 (not the same).
# 2. **Samplers with the exact score**, no training: the 12 equivalent poses of a tetrahedron are
#    a point-mass mixture whose noisy score is known in closed form (`MixtureOracle`). Random walk
#    (paper Eq. 7), ancestral (the authors' code) and few-step (posediff) at 5 and 100 steps, on
#    the equal-weight mixture and on one with unequal weights (which the symmetric one cannot test).
# 3. **Training the toy** (`conf/experiment/toy_so3.yaml`): the condition is a symmetry-invariant
#    code of the pose, so the target is the full set of equivalent poses — 12 / 24 / 60 modes for
#    tet / cube / icosa, a circle (cone) or two (cylinder).
# 4. **Beyond the paper**: `modes()` turns 500 samples into "K poses with weights", and
#    `log_likelihood()` (probability-flow ODE) ranks poses: equivalent poses score alike.
#
# `POSEDIFF_FAST=1` (the default, and what the tests run) trains a narrow network for 150 steps —
# enough to run every cell, not to learn the toy. `POSEDIFF_FAST=0` trains as
# `conf/experiment/toy_so3.yaml` does (5000 steps, about 12 minutes on one core).

# %%
import functools
import math
import os
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import lightning as L
import matplotlib.pyplot as plt
import torch

from posediff.data.toy import SymmetryToyDataModule
from posediff.diffusion import (
    IGSO3,
    AncestralSampler,
    ConcentratedGaussian,
    Diffusion,
    FewStepSampler,
    GeodesicRandomWalk,
    MixtureOracle,
    PowerSchedule,
    log_likelihood,
    modes,
)
from posediff.diffusion.igso3 import eps_from_sigma, igso3_log_density
from posediff.lie import SO3
from posediff.metrics import mode_coverage, rotation_spread_deg
from posediff.models import PoseDiffusionModule
from posediff.nn import MLPDenoiser
from posediff.symmetry import (
    SHAPES,
    equivalent_rotations,
    is_continuous,
    min_angle_to_equivalents,
    rotation_angle,
    symmetry_group,
)
from posediff.viz import plot_so3, save_figure

FAST = os.environ.get("POSEDIFF_FAST", "1") == "1"
OUT = Path(os.environ.get("POSEDIFF_NOTEBOOK_OUT", "outputs/notebooks"))
OUT.mkdir(parents=True, exist_ok=True)
T_START = time.perf_counter()
# One intra-op thread: these networks are too small to gain from more, and on a busy machine two
# OpenMP threads contending for two loaded cores made this notebook five times slower.
torch.set_num_threads(1)
L.seed_everything(0, verbose=False)
warnings.filterwarnings("ignore", ".*does not have many workers.*")
so3 = SO3()


def figure_mollweide(rows: int, cols: int, width: float = 5.0):  # noqa: ANN201
    """A figure of ``rows × cols`` Mollweide axes."""
    fig = plt.figure(figsize=(width * cols, 0.58 * width * rows))
    axes = [fig.add_subplot(rows, cols, i + 1, projection="mollweide") for i in range(rows * cols)]
    return fig, axes


def save(fig, name: str) -> None:  # noqa: ANN001
    path = save_figure(fig, OUT / name, dpi=110)
    plt.close(fig)
    print("figure:", path)


# %% [markdown]
# ## 1. The forward process
#
# `ConcentratedGaussian("so3").sample(R, σ)` returns `R·Exp(z)` with `z ~ N(0, σ² I₃)`. On the
# Mollweide map (see `posediff.viz.mollweide`) a point is the direction of the rotated x-axis and
# its colour the roll about it; the circle is the clean rotation.

# %%
R0 = so3.exp(torch.tensor([0.4, -0.6, 0.9], dtype=torch.float64))
gauss = ConcentratedGaussian("so3")
gen = torch.Generator().manual_seed(1)
n_fwd = 300 if FAST else 1000
fig, axes = figure_mollweide(2, 2)
for ax, sigma in zip(axes, [0.05, 0.2, 0.5, 1.0], strict=True):
    noisy, _ = gauss.sample(R0.expand(n_fwd, 3, 3), sigma, generator=gen)
    angle = torch.rad2deg(rotation_angle(R0.mT @ noisy))
    plot_so3(noisy, ax=ax, gt=R0, title=f"σ = {sigma}", colorwheel=ax is axes[-1])
    print(f"σ = {sigma:4}: mean angle to R0 = {angle.mean():5.1f}°")
save(fig, "02_forward.png")

# %% [markdown]
# Angle of the perturbation, concentrated Gaussian vs `IG_SO(3)` (`ε = σ²/2`, so the two agree as
# σ → 0). The curve is the exact `IG_SO(3)` angle density `(1 − cos ω)/π · f_ε(ω)`. At σ = 1 the
# laws differ: the Gaussian's angle is the χ₃ law of `|z|` folded at π (`|z|` > π about 2 % of the
# time, wrapping to `2π − |z|`), with more mass near π than `IG_SO(3)`.

# %%
igso3 = IGSO3("so3")
n_hist = 20_000 if FAST else 50_000
omega = torch.linspace(1e-4, math.pi, 400, dtype=torch.float64)
fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
for ax, sigma in zip(axes, [0.2, 1.0], strict=True):
    sig = torch.full((n_hist,), sigma, dtype=torch.float64)
    a_gauss = rotation_angle(so3.exp(gauss.sample_tangent(sig, generator=gen)))
    a_ig = rotation_angle(so3.exp(igso3.sample_tangent(sig, generator=gen)))
    bins = torch.linspace(0, min(math.pi, 6 * sigma), 61).numpy()
    ax.hist(a_gauss.numpy(), bins=bins, density=True, alpha=0.5, label="concentrated Gaussian")
    ax.hist(a_ig.numpy(), bins=bins, density=True, alpha=0.5, label="IG_SO(3) samples")
    dens = (1 - omega.cos()) / math.pi * igso3_log_density(omega, eps_from_sigma(sigma)).exp()
    keep = omega <= bins[-1]
    ax.plot(omega[keep].numpy(), dens[keep].numpy(), "k", lw=1.2, label="IG_SO(3) density")
    ax.set_title(f"σ = {sigma}")
    ax.set_xlabel("rotation angle ω (rad)")
    p_wrap = (sigma * torch.randn(n_hist, 3, generator=gen).norm(dim=-1) > math.pi).double().mean()
    print(
        f"σ = {sigma}: mean angle Gaussian {a_gauss.mean():.4f}, IG_SO(3) {a_ig.mean():.4f} rad; "
        f"P(|z| > π) = {p_wrap:.4f}"
    )
axes[0].legend(fontsize=8)
save(fig, "02_igso3_vs_gaussian.png")

# %% [markdown]
# ## 2. Samplers with the exact score
#
# Target: the 12 equivalent poses `R0·S`, `S` in the tetrahedral group. `MixtureOracle` is the
# exact minimiser of the training loss for this target (the posterior-weighted surrogate target),
# so the samplers are judged without any training error. The prior is Haar-uniform (`prior="haar"`,
# as the toy config), the schedule the authors' power schedule (σ from 1e-4 to 0.985).

# %%
diffusion = Diffusion(ConcentratedGaussian("so3"), PowerSchedule(), prior="haar")
centers = equivalent_rotations("tet", R0)  # (12, 3, 3)
assert centers.shape[0] == symmetry_group("tet").shape[0] == 12
oracle = MixtureOracle(diffusion, centers)
samplers = {
    "random_walk": GeodesicRandomWalk(diffusion),
    "ancestral": AncestralSampler(diffusion),
    "few_step": FewStepSampler(diffusion),
}
n_oracle = 600 if FAST else 1000
fig, axes = figure_mollweide(3, 2, width=4.6)
ax_iter = iter(axes)
print(f"{'sampler':12s} {'steps':>5s} {'spread °':>9s} {'coverage':>9s}  mode weights (1/12 = 0.083)")
for name, sampler in samplers.items():
    for steps in (5, 100):
        g = torch.Generator().manual_seed(2)
        x = sampler.sample(oracle, None, n_oracle, steps, generator=g, dtype=torch.float64)  # (1, N, 3, 3)
        spread = rotation_spread_deg("tet", x, R0[None]).item()
        cover = mode_coverage("tet", x, R0[None]).item()
        nearest = torch.einsum("nij,kij->nk", x[0], centers).argmax(-1)  # max tr(Cᵀ X): nearest mode
        weights = torch.bincount(nearest, minlength=12) / n_oracle
        print(
            f"{name:12s} {steps:5d} {spread:9.4f} {cover:9.3f}  "
            f"min {weights.min():.3f}, max {weights.max():.3f}"
        )
        ax = next(ax_iter)
        plot_so3(
            x[0],
            ax=ax,
            gt=centers,
            title=f"{name}, {steps} steps",
            gt_radius=8,
            colorwheel=False,
            marker_size=14,
        )
save(fig, "02_oracle_samplers.png")

# %% [markdown]
# Spread is the mean angle from a sample to the nearest equivalent pose; coverage the fraction of
# the 12 poses with a sample within 5°. With the exact score every sampler puts every sample on a
# mode, even with 5 steps: the last step predicts the clean pose at σ_min = 1e-4, which for the
# exact denoiser is the nearest mode itself. The weights come out even for every sampler too, but
# that is forced by symmetry (the Haar prior and the 12-mode target are both invariant under the
# tetrahedral group), so it tests nothing. An honest test of the weights needs a target without
# that symmetry: the same 12 poses with weights ∝ 1, 2, …, 12.

# %%
w_target = torch.arange(1, 13, dtype=torch.float64)
w_target = w_target / w_target.sum()
weighted = MixtureOracle(diffusion, centers, w_target)
n_weighted = 2000 if FAST else 8000
# total variation from the multinomial sampling noise alone, E ½Σ|ŵ − w| ≈ ½Σ √(2w(1−w)/(πN))
noise_tv = 0.5 * (2 * w_target * (1 - w_target) / (math.pi * n_weighted)).sqrt().sum()
print(f"weights ∝ 1..12, {n_weighted} samples; sampling noise alone gives TV ≈ {noise_tv:.3f}")


def mode_weights(x: torch.Tensor) -> torch.Tensor:
    """Fraction of the samples ``x (N, 3, 3)`` nearest to each of the 12 modes (max tr(Cᵀ X))."""
    nearest = torch.einsum("nij,kij->nk", x, centers).argmax(-1)
    return torch.bincount(nearest, minlength=12) / x.shape[0]


weight_samplers = {
    "random_walk": samplers["random_walk"],
    "random_walk sde": GeodesicRandomWalk(diffusion, noise="sde"),
    "ancestral": samplers["ancestral"],
    "few_step": samplers["few_step"],
}
fig, axes = plt.subplots(1, 2, figsize=(12, 3.4), sharey=True)
for ax, steps in zip(axes, (5, 100), strict=True):
    ax.bar(torch.arange(12) - 0.32, w_target, width=0.16, color="k", label="target")
    for j, (name, sampler) in enumerate(weight_samplers.items()):
        g = torch.Generator().manual_seed(6)
        x = sampler.sample(weighted, None, n_weighted, steps, generator=g, dtype=torch.float64)
        emp = mode_weights(x[0])
        tv = 0.5 * (emp - w_target).abs().sum()
        print(f"{name:16s} {steps:4d} steps: total variation to the target weights {tv:.3f}")
        ax.bar(torch.arange(12) - 0.16 + 0.16 * j, emp, width=0.16, label=f"{name} (TV {tv:.3f})")
    ax.set_title(f"{steps} steps")
    ax.set_xlabel("mode")
    ax.legend(fontsize=7)
axes[0].set_ylabel("fraction of samples")
save(fig, "02_oracle_weights.png")


class TruePriorDiffusion(Diffusion):
    """The same process, but the reverse process starts from the true noisy marginal at σ_max."""

    def prior(self, batch_shape, *, generator=None, dtype=None, device=None):  # noqa: ANN001, ANN201
        n = math.prod(batch_shape)
        k = torch.multinomial(w_target, n, replacement=True, generator=generator)
        x, _ = self.kernel.sample(centers[k].to(dtype), self.schedule.sigma_max, generator=generator)
        return x.reshape(*batch_shape, 3, 3)


true_prior = TruePriorDiffusion(ConcentratedGaussian("so3"), PowerSchedule(), prior="haar")
for steps in (5, 100):
    g = torch.Generator().manual_seed(6)
    x = FewStepSampler(true_prior).sample(weighted, None, n_weighted, steps, generator=g, dtype=torch.float64)
    tv = 0.5 * (mode_weights(x[0]) - w_target).abs().sum()
    print(f"few_step from the true σ_max marginal, {steps:3d} steps: TV {tv:.3f}")

# %% [markdown]
# * The geodesic random walk as in the paper (Eq. 7: `X·Exp(ε s + √(2ε) n)` with the reverse-diffusion
#   step `ε = σ_t² − σ_p²`) injects twice the variance of the reverse SDE and flattens the weights
#   towards uniform — badly at 5 steps, still visibly at 100 (full run: TV 0.14 and 0.06). With
#   `noise="sde"` (`√ε n`) it is a consistent discretisation and, at 100 steps, on a par with
#   ancestral sampling (TV 0.03).
# * The deterministic few-step sampler (an Euler scheme for the probability-flow ODE) is close at 5
#   steps but does not improve with more (TV 0.07 at 5 steps, 0.06 at 100): its remaining error
#   is the prior. The true noisy marginal at σ_max ≈ 0.985 is not yet uniform, and a deterministic
#   flow cannot correct a wrong start; started from the true marginal it is within sampling noise
#   (TV 0.011; noise alone 0.014 at 8000 samples). The stochastic samplers wash out most, not all,
#   of the prior error (ancestral at 100 steps: 0.03).

# %% [markdown]
# ## 3. Training the toy
#
# Settings of `conf/experiment/toy_so3.yaml`: SO(3), power schedule, Haar prior, the few-step
# sampler, Adam 1e-3 → 1e-4 over the second half. The condition is `[one-hot shape, canonical
# rotation]` (14 numbers). The full run uses the config's network (width 256, 128 frequencies)
# and batch (32 inputs × 64 noisy poses a step), about 0.13 s a step on one CPU core; fast mode
# trains a width-64 network with 16 frequencies on 16 × 16 noisy poses, only to run every cell.

# %%
if FAST:
    CFG = dict(
        max_steps=150,
        hidden=64,
        freqs=16,
        batch=16,
        num_noisy=16,
        num_train=4000,
        num_poses=4,
        test_per_shape=2,
        eval_samples=50,
        eval_steps=10,
        plot_samples=500,
        plot_steps=10,
        ll_steps=20,
    )
else:  # conf/experiment/toy_so3.yaml
    CFG = dict(
        max_steps=5000,
        hidden=256,
        freqs=128,
        batch=32,
        num_noisy=64,
        num_train=100_000,
        num_poses=4,
        test_per_shape=4,
        eval_samples=200,
        eval_steps=100,
        plot_samples=500,
        plot_steps=50,
        ll_steps=100,
    )
print(CFG)

torch.manual_seed(0)
dm = SymmetryToyDataModule(
    "so3",
    num_train=CFG["num_train"],
    num_poses=CFG["num_poses"],
    num_test_per_shape=CFG["test_per_shape"],
    batch_size=CFG["batch"],
)
dm.setup()
denoiser = MLPDenoiser(
    cond_dim=dm.cond_dim,
    in_dim=3,
    out_dim=3,
    hidden_dim=CFG["hidden"],
    num_frequencies=CFG["freqs"],
    time_dim=CFG["hidden"],
    pose_min_period=0.0625,  # faster pose frequencies than the paper's (docs/sampling.md, "The CPU toy")
    pose_max_period=10.0,
)
toy_diffusion = Diffusion(ConcentratedGaussian("so3"), PowerSchedule(), prior="haar")
module = PoseDiffusionModule(
    toy_diffusion,
    denoiser,
    functools.partial(FewStepSampler, renoise=1.0),  # predict clean, re-noise: the sharpest here
    num_noisy=CFG["num_noisy"],
    lr=1e-3,
    lr_final=1e-4,
)
test = dm.test
k = CFG["test_per_shape"]


def evaluate(tag: str) -> dict[str, float]:
    """Spread (°) per shape over every test input, ``eval_samples`` samples each; mode coverage
    (fraction of the equivalent poses with a sample within 5°) for the polyhedra."""
    module.eval()
    out, text = {}, []
    g = torch.Generator().manual_seed(3)
    for i, shape in enumerate(SHAPES):
        sl = slice(i * k, (i + 1) * k)
        x = module.sample(test.cond[sl], CFG["eval_samples"], CFG["eval_steps"], generator=g).double()
        R_gt = test.rotation[sl].double()
        out[shape] = rotation_spread_deg(shape, x, R_gt).mean().item()
        cover = "" if is_continuous(shape) else f" (coverage {mode_coverage(shape, x, R_gt).mean():.2f})"
        text.append(f"{shape} {out[shape]:.1f}°{cover}")
    print(f"spread, {tag}: " + ", ".join(text))
    return out


spread_before = evaluate("untrained")

# %%
trainer = L.Trainer(
    max_steps=CFG["max_steps"],
    logger=False,
    enable_checkpointing=False,
    enable_progress_bar=False,
    enable_model_summary=False,
    accelerator="cpu",
    devices=1,
)
t0 = time.perf_counter()
module.train()
trainer.fit(module, datamodule=dm)
print(f"trained {trainer.global_step} steps in {time.perf_counter() - t0:.1f} s")
spread_after = evaluate("trained")

# %%
loss = torch.tensor(module.loss_history)
win = max(1, len(loss) // 30)
smooth = torch.nn.functional.avg_pool1d(loss[None, None], win, stride=1)[0, 0]
fig, ax = plt.subplots(figsize=(6, 3.2))
ax.plot(loss.numpy(), lw=0.6, alpha=0.4, label="per step")
ax.plot(torch.arange(len(smooth)) + win // 2, smooth.numpy(), lw=1.5, label=f"moving mean ({win})")
ax.set_yscale("log")
ax.set_xlabel("step")
ax.set_ylabel("DSM loss (σ²-weighted)")
ax.legend()
save(fig, "02_loss.png")
print(f"loss: first {loss[:win].mean():.3f}, last {loss[-win:].mean():.3f}")

# %% [markdown]
# What the full run (5000 steps, 16 minutes of training on one busy core) learned, measured with
# the re-noising few-step sampler at 100 steps: tetrahedron 0.5° (all 12 modes covered), cube
# 1.6° (coverage 0.99), cone 0.5°, cylinder 0.7° — from 51°, 41°, 88° and 57° untrained; the
# icosahedron only in part (7.1°, coverage 0.73: its 60 modes are 37° apart). A 15000-step run
# brings the icosahedron to 0.9° (docs/sampling.md, "The CPU toy").
#
# One test input per shape, 500 samples of the trained model; the circles are the equivalent
# poses (for cone and cylinder the continuous set, drawn every 10°).

# %%
first = torch.arange(len(SHAPES)) * k
g = torch.Generator().manual_seed(4)
toy_samples = module.sample(test.cond[first], CFG["plot_samples"], CFG["plot_steps"], generator=g)
fig, axes = figure_mollweide(2, 3, width=4.6)
for i, shape in enumerate(SHAPES):
    R_gt = test.rotation[first[i]].double()
    kw = {"step_deg": 10.0} if is_continuous(shape) else {}
    gt = equivalent_rotations(shape, R_gt, **kw)
    spread = rotation_spread_deg(shape, toy_samples[i].double(), R_gt).item()
    plot_so3(
        toy_samples[i],
        ax=axes[i],
        gt=gt,
        gt_radius=4 if is_continuous(shape) else 6,
        title=f"{shape}: spread {spread:.1f}°",
        colorwheel=False,
    )
axes[-1].set_visible(False)
save(fig, "02_toy_samples.png")

# %% [markdown]
# ## 4. Beyond the paper: modes and likelihoods
#
# `modes()` clusters the 500 tetrahedron samples (radius 10°) and returns each cluster's Karcher
# mean with its weight: a well-trained model gives 12 modes of weight ≈ 1/12. The full run gives 13
# clusters: 12 within 10° of the 12 equivalent poses, holding 99.8 % of the samples, with weights
# from 0.036 to 0.124 (not yet equal), and one stray sample.

# %%
R_tet = test.rotation[first[0]].double()
tet_gt = equivalent_rotations("tet", R_tet)
m = modes(toy_samples[0].double(), so3, radius_deg=10.0)
w = m.weights.tolist()
print(f"{len(m)} modes, weights " + ", ".join(f"{v:.3f}" for v in w[:15]) + (" …" if len(w) > 15 else ""))
near = torch.rad2deg(min_angle_to_equivalents("tet", m.poses, R_tet)) < 10.0
true_found = (torch.rad2deg(rotation_angle(tet_gt[:, None].mT @ m.poses[None])) < 10.0).any(-1)
print(
    f"{int(near.sum())} of the {len(m)} modes are within 10° of an equivalent pose, holding "
    f"{m.weights[near].sum():.1%} of the samples; "
    f"{int(true_found.sum())} of the 12 equivalent poses have a mode within 10°"
)
fig, ax = figure_mollweide(1, 1, width=6)
plot_so3(
    m.poses,
    ax=ax[0],
    weights=m.weights,
    gt=tet_gt,
    gt_radius=8,
    title=f"tet: {len(m)} mode means (area ∝ weight)",
)
save(fig, "02_modes.png")

# %% [markdown]
# `log_likelihood()` integrates the probability-flow ODE from σ_min to σ_max (the network is the
# `denoise_fn`, `module.encode(cond)` its condition) and returns `log p_{σ_min}(X)`. Scored: the 12
# equivalent poses, the ground truth turned by 5°, 20° and 45°, and a Haar-random rotation
# (`off °`: the angle to the nearest equivalent pose). The exact oracle of the same 12-point target
# is the reference. At the modes it gives the exact value (about 22.4; the small excess is the Haar
# prior standing in for the true marginal at σ_max). Off the support the true log density at
# σ_min = 1e-4 is of order `−θ²/(2σ_min²)`, i.e. −10⁵ and below; the ODE, stiff there, returns
# values that are far lower than at the modes but not converged in the number of steps — use them
# to rank, not as numbers. The untrained model gives `−log 8π² ≈ −4.37` everywhere (the Haar
# density); the full run gives 9.6 ± 1.5 at the 12 equivalent poses (the oracle: 22.5) and lower
# values the further a pose is from them (−2.4, −3.5, −7.3, −9.9 for 5°, 20°, 45° and the random
# pose): the ranking is right, the numbers are not converged.

# %%
g = torch.Generator().manual_seed(5)
axis = torch.nn.functional.normalize(torch.randn(3, generator=g, dtype=torch.float64), dim=0)
perturbed = {f"{d}°": R_tet @ so3.exp(math.radians(d) * axis) for d in (5, 20, 45)}
perturbed["random"] = so3.sample_uniform((), generator=g, dtype=torch.float64)
queries = torch.cat([tet_gt, torch.stack(list(perturbed.values()))])[None]  # (1, 16, 3, 3)
labels = [f"equiv {i}" for i in range(12)] + list(perturbed)
off = torch.rad2deg(min_angle_to_equivalents("tet", queries[0], R_tet))  # angle to the nearest mode

module.eval()
feature = module.encode(test.cond[first[:1]])
t0 = time.perf_counter()
ll_model = log_likelihood(module.forward, toy_diffusion, queries.float(), feature, num_steps=CFG["ll_steps"])
ll_oracle = log_likelihood(
    MixtureOracle(toy_diffusion, tet_gt), toy_diffusion, queries, None, num_steps=CFG["ll_steps"]
)
print(f"log-likelihood ({CFG['ll_steps']} ODE steps, {time.perf_counter() - t0:.1f} s)")
print(f"{'pose':>9s} {'off °':>6s} {'model':>9s} {'oracle':>9s}")
for lab, o, a, b in zip(labels, off.tolist(), ll_model[0].tolist(), ll_oracle[0].tolist(), strict=True):
    print(f"{lab:>9s} {o:6.1f} {a:9.2f} {b:9.2f}")
eq = ll_model[0, :12]
print(
    f"model: equivalent poses {eq.mean():.2f} ± {eq.std():.2f}, the others {ll_model[0, 12:].mean():.2f} "
    f"(oracle at the modes: {ll_oracle[0, :12].mean():.2f}; exact −log 12 − 1.5·log(2πσ_min²) = "
    f"{-math.log(12) - 1.5 * math.log(2 * math.pi * toy_diffusion.schedule.sigma_min**2):.2f})"
)

# %%
print(f"notebook ran in {time.perf_counter() - T_START:.1f} s ({'fast' if FAST else 'full'} mode)")
