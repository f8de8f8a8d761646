# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
# ---

# %% [markdown]
# # 03 — Quickstart: SYMSOL-T images → pose distributions, in Python
#
# The path `make demo` takes with the CLI, one step at a time through the Python API:
# 1. **Render** a small SYMSOL-T (the five shapes at random poses and positions, 128 px) with
#    `posediff.data.symsol.render_dataset` — what `posediff data render` calls.
# 2. **Build** the model of `conf/experiment/quickstart.yaml` with Hydra's compose + instantiate
#    (ResNet18 encoder run once per image, MLP denoiser, SE(3) diffusion) and **train** it with
#    Lightning.
# 3. **Evaluate**: rotation spread, translation error and recall before and after training.
# 4. **Predict** one test image: 1000 hypotheses, their modes, the Mollweide SO(3) plot and the
#    top modes drawn over the image.
#
# `POSEDIFF_FAST=1` (the tests) renders a few images and trains 10 steps — enough to run every
# cell, not to learn. `POSEDIFF_FAST=0` uses the experiment's own sizes (as `make demo`; about
# 12 minutes on 2 CPU cores).

# %%
import os
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import lightning as L
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from posediff.config import register_resolvers
from posediff.data.symsol import render_dataset
from posediff.evaluation import evaluate, predict, run_table, save_prediction

FAST = os.environ.get("POSEDIFF_FAST", "1") != "0"
OUT = Path(os.environ.get("POSEDIFF_NOTEBOOK_OUT", "outputs/notebooks"))
OUT.mkdir(parents=True, exist_ok=True)
warnings.filterwarnings("ignore", message=".*does not have many workers.*")
torch.set_num_threads(min(2, os.cpu_count() or 1))

# %% [markdown]
# ## 1. Render a small SYMSOL-T
# Shards of PNG-compressed images plus an index of poses; re-running resumes or skips.

# %%
from posediff.cli import config_dir

DATA = OUT / "symsolt_quickstart"
n_train, n_test = (8, 2) if FAST else (2000, 20)
for split, n in (("train", n_train), ("test", n_test)):
    summary = render_dataset(
        DATA, dataset="symsolt", split=split, n_per_shape=n, image_size=128, progress=False
    )
    print(summary.line())

# %% [markdown]
# ## 2. The quickstart model, from its Hydra config
# `compose` reads `conf/fit.yaml` with `+experiment=quickstart` exactly as `posediff fit` does;
# `instantiate` builds every object from its `_target_`.

# %%
register_resolvers()
overrides = ["+experiment=quickstart", f"data.root={DATA}", f"data.n_per_shape_test={n_test}"]
overrides += ["trainer.logger=null", "trainer.callbacks=null", f"trainer.default_root_dir={OUT}"]
if FAST:
    overrides += ["trainer.max_steps=10", "data.batch_size=4", "module.num_noisy=8", "sampler.num_steps=10"]
with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
    cfg = compose(config_name="fit", overrides=overrides)
L.seed_everything(cfg.seed, verbose=False)
module = instantiate(cfg.module)
datamodule = instantiate(cfg.data)
datamodule.setup("fit")
print(module.encoder)
print(f"group {module.group.name}, {sum(p.numel() for p in module.parameters()) / 1e6:.1f} M parameters")

# %% [markdown]
# ## 3. Evaluate, train, evaluate
# 200 hypotheses per test image; spread = mean angle to the nearest equivalent pose.

# %%
num_samples = 20 if FAST else 200
before = evaluate(module, datamodule.test_dataloader(), datamodule.shapes, num_samples=num_samples)
print("untrained:\n" + run_table(before))

trainer = L.Trainer(
    max_steps=int(cfg.trainer.max_steps),
    accelerator="cpu",
    logger=False,
    enable_checkpointing=False,
    enable_progress_bar=False,
    enable_model_summary=False,
    num_sanity_val_steps=0,
    limit_val_batches=0,
)
start = time.perf_counter()
trainer.fit(module, datamodule=datamodule)
print(f"trained {trainer.global_step} steps in {time.perf_counter() - start:.0f} s")
after = evaluate(module, datamodule.test_dataloader(), datamodule.shapes, num_samples=num_samples)
print("trained:\n" + run_table(after))

# %% [markdown]
# ## 4. Predict one test image
# `predict` samples 1000 hypotheses and clusters them into weighted modes; `save_prediction`
# writes `poses.npz` / `poses.json`, the Mollweide plot (samples as dots, modes as discs, every
# pose equivalent to the ground truth as a circle), the translations and the overlay.

# %%
from posediff.data.symsol.render import SCENE_DISTANCE, intrinsics
from posediff.symmetry import SHAPES

batch = next(iter(datamodule.test_dataloader()))
i = 0
shape = SHAPES[int(batch["shape"][i])]
pred = predict(module, batch["image"][i], num_samples=100 if FAST else 1000, trajectory=True)
files = save_prediction(
    pred,
    OUT / "quickstart_predict",
    image=batch["image"][i],
    K=intrinsics(128),
    camera_offset=torch.tensor([0.0, 0.0, SCENE_DISTANCE]).numpy(),
    shape=shape,
    gt_pose=batch["pose"][i],
)
print(shape, pred.modes.summary())
for name, path in files.items():
    print(f"{name}: {path}")
