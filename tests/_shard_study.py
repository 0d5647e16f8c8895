"""A toy sharded study for tests/test_cli.py: per run, a few draws of the shard generator;
``cfg["fail_run"]`` makes the shard holding that run raise."""

import torch

NAME = "shard-toy"
DESCRIPTION = "toy sharded study (tests only)"


def run_shard(cfg, runs, *, generator, device, progress=False):
    if cfg.get("fail_run") in runs:
        raise FloatingPointError(f"run {cfg['fail_run']} diverged")
    draws = torch.rand(len(runs), 3, generator=generator, device=device)
    return {"draws": draws, "run": torch.tensor(list(runs))}, {"toy": 0.5}
