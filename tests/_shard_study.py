"""A toy sharded study for tests/test_cli.py: per run, a few draws of the shard generator;
``fail_run`` makes the shard holding that run raise."""

from dataclasses import dataclass

import torch

from torchmcmcpf.experiments._study import Settings, Study, option


@dataclass(frozen=True)
class ToySettings(Settings):
    runs: int = option(5, help="runs")
    shard_size: int = option(2, cli=False)
    fail_run: int | None = option(None, cli=False)


class Toy(Study[ToySettings]):
    name = "shard-toy"
    description = "toy sharded study (tests only)"

    def run_shard(self, settings, runs, *, generator, device, progress=False):
        if settings.fail_run in runs:
            raise FloatingPointError(f"run {settings.fail_run} diverged")
        draws = torch.rand(len(runs), 3, generator=generator, device=device)
        return {"draws": draws, "run": torch.tensor(list(runs))}, {"toy": 0.5}


STUDY = Toy()
