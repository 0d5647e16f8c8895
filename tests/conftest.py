import pytest
import torch


@pytest.fixture
def gen():
    """A fresh, seeded generator: every random draw in the tests goes through one."""
    return torch.Generator().manual_seed(1234)
