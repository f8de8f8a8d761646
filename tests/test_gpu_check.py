"""The GPU check runs end to end on the CPU in its tiny mode (so that it cannot break unnoticed before
a GPU comes), and the compiled sampler step gives the eager samples."""

import json
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def test_the_tiny_gpu_check_runs_every_section(tmp_path: Path) -> None:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import gpu_check
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    out = tmp_path / "gpu_check_cpu.json"
    assert gpu_check.main(["--tiny", "--out", str(out), "--workdir", str(tmp_path / "work")]) == 0
    r = json.loads(out.read_text())
    assert set(r["sections"]) == {"render", "train", "sample", "learn"}
    assert all("error" not in s for s in r["sections"].values()), r["sections"]
    assert r["sections"]["render"]["images_per_s"] > 0 and r["sections"]["render"]["renderer"]
    assert {row["variant"] for row in r["sections"]["train"]["rows"]} == {"eager", "channels_last"}
    modes = {(row["mode"], row["hypotheses"]) for row in r["sections"]["sample"]["rows"]}
    assert modes == {("eager", 4), ("compiled", 4)}
    assert set(r["sections"]["learn"]["spread_deg"]) == {"tet", "cube", "icosa", "cone", "cyl"}
    md = out.with_suffix(".md").read_text()
    assert "## sample" in md and "| dtype | mode | steps | hypotheses |" in md


def test_the_compiled_step_samples_what_eager_samples() -> None:
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from posediff.cli import config_dir
    from posediff.config import register_resolvers
    from posediff.evaluation.sampling import accelerated_denoise_fn

    register_resolvers()
    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        cfg = compose("fit", overrides=["+experiment=toy_se3", "denoiser.hidden_dim=16", "sampler=few_step",
                                        "sampler.renoise=0.5"])  # fmt: skip
    torch.manual_seed(0)
    module = instantiate(cfg.module).eval()
    dm = instantiate(cfg.data)
    dm.setup("test")
    cond = module.encode(next(iter(dm.test_dataloader()))[module.cond_key][:3])
    runs = {}
    for mode in ("eager", "compiled"):
        fn = accelerated_denoise_fn(module, mode)
        with torch.no_grad():
            runs[mode] = module.sampler.sample(fn, cond, 8, 4, torch.Generator().manual_seed(1))
    torch.testing.assert_close(runs["compiled"], runs["eager"], atol=1e-4, rtol=1e-4)
    with pytest.raises(ValueError, match="unknown mode"):
        accelerated_denoise_fn(module, "fast")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="needs a CUDA device"):
            accelerated_denoise_fn(module, "cudagraphs")
