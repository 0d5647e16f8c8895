"""``Filter.step``'s two paths (issue 26): a state the filter made itself (``init``, ``step``,
``forward``) and unchanged since skips the full state check; any other state, or one changed
in place, is checked in full as before.
"""

import copy
import math
import pickle

import pytest
import torch

from torchmcmcpf import ConstantVelocity, LinearGaussian
from torchmcmcpf.filters import IPMCMCFilter, SIRFilter

B, N, K, T = 2, 32, 1, 4


def build(kind="sir", n=N):
    motion, sensor = ConstantVelocity(1.0, 0.1).double(), LinearGaussian.position(1.0).double()
    if kind == "sir":
        filt = SIRFilter(motion, sensor, n)
    else:
        filt = IPMCMCFilter(motion, sensor, n, num_chains=4, burn_in=2)
    g = torch.Generator().manual_seed(0)
    x0 = torch.randn(B, n, K, 4, generator=g, dtype=torch.float64)
    z = torch.randn(T, B, K, 2, generator=g, dtype=torch.float64)
    return filt, x0, z


@pytest.fixture
def full_checks(monkeypatch):
    """Counts the full state checks of every filter (``Filter._check_state_tensors``)."""
    from torchmcmcpf.filters.base import Filter

    calls = []
    original = Filter._check_state_tensors

    def counting(self, x, exists):
        calls.append(x)
        return original(self, x, exists)

    monkeypatch.setattr(Filter, "_check_state_tensors", counting)
    return calls


@pytest.mark.parametrize("kind", ["sir", "ipmcmc"])
def test_own_states_skip_the_full_check(kind, full_checks):
    filt, x0, z = build(kind)
    g = torch.Generator().manual_seed(1)
    state = filt.init(x0)
    assert len(full_checks) == 1  # init checks what it is given
    for t in range(T):
        state, _ = filt.step(state, z[t], generator=g)
    assert len(full_checks) == 1  # its own outputs, unchanged: no second check
    res = filt(z, init=x0, generator=g)  # forward checks its init once ...
    assert len(full_checks) == 2
    filt.step(res.state, z[0], generator=g)  # ... and its final state is the filter's own
    assert len(full_checks) == 2


def test_the_same_state_stepped_again_stays_trusted(full_checks):
    # the benchmarks step one initial state again and again
    filt, x0, z = build()
    state = filt.init(x0)
    for _ in range(10):
        filt.step(state, z[0], generator=torch.Generator().manual_seed(2))
    assert len(full_checks) == 1


def test_both_paths_give_the_same_bits():
    filt, x0, z = build()
    trusted, _ = filt.step(filt.init(x0), z[0], generator=torch.Generator().manual_seed(3))
    foreign = filt.init(x0)._replace(x=x0.clone())  # a new tensor: the full check
    checked, _ = filt.step(foreign, z[0], generator=torch.Generator().manual_seed(3))
    assert torch.equal(trusted.x, checked.x) and torch.equal(trusted.log_w, checked.log_w)


def test_a_foreign_state_is_checked_in_full(full_checks):
    filt, x0, z = build()
    state = filt.init(x0)
    bad = state._replace(x=state.x.clone().index_fill_(1, torch.tensor([3]), math.nan))
    with pytest.raises(ValueError, match=rf"init contains {B * K * 4} NaN"):
        filt.step(bad, z[0], generator=torch.Generator().manual_seed(0))
    other, _, _ = build()  # another filter's state: that filter vouches for it, this one does not
    n_before = len(full_checks)
    filt.step(other.init(x0.clone()), z[0], generator=torch.Generator().manual_seed(0))
    assert len(full_checks) == n_before + 2  # other.init, then this filter's step


@pytest.mark.parametrize("change", ["setitem", "add_", "view"])
def test_a_state_changed_in_place_is_checked_in_full(change):
    filt, x0, z = build()
    g = torch.Generator().manual_seed(1)
    state, _ = filt.step(filt.init(x0), z[0], generator=g)
    if change == "setitem":
        state.x[0, 5, 0, 2] = math.inf
    elif change == "add_":
        state.x.add_(math.nan)
    else:  # through a view: the version counter is shared
        state.x.view(-1)[7] = math.nan
    with pytest.raises(ValueError, match="init contains .* NaN/inf"):
        filt.step(state, z[1], generator=g)


def test_a_state_of_the_wrong_size_is_refused():
    filt, x0, z = build()
    small, x_small, _ = build(n=8)
    state = small.init(x_small)
    with pytest.raises(ValueError, match="init has shape"):
        filt.step(state, z[0], generator=torch.Generator().manual_seed(0))


def test_changed_existence_flags_are_checked(full_checks):
    filt, x0, z = build()
    exists = torch.ones(B, N, K, dtype=torch.bool)
    state = filt.init(x0, exists)
    assert len(full_checks) == 1
    filt.step(state, z[0], generator=torch.Generator().manual_seed(0))
    assert len(full_checks) == 1
    flags = state.exists.clone()
    filt.step(state._replace(exists=flags), z[0], generator=torch.Generator().manual_seed(0))
    assert len(full_checks) == 2
    filt.step(state._replace(exists=None), z[0], generator=torch.Generator().manual_seed(0))
    assert len(full_checks) == 3
    flags[0, 0, 0] = False  # changed after this filter saw it
    filt.step(state._replace(exists=flags), z[0], generator=torch.Generator().manual_seed(0))
    assert len(full_checks) == 4


def test_inference_mode_states_are_always_checked(full_checks):
    filt, x0, z = build()
    with torch.inference_mode():
        state = filt.init(x0.clone())
        state, _ = filt.step(state, z[0], generator=torch.Generator().manual_seed(0))
        filt.step(state, z[1], generator=torch.Generator().manual_seed(0))
    assert len(full_checks) == 3  # no version counter to vouch for them


def test_filters_still_copy_and_pickle_and_a_copy_trusts_nothing(full_checks):
    filt, x0, z = build()
    state = filt.init(x0)
    for clone in (copy.deepcopy(filt), pickle.loads(pickle.dumps(filt))):
        n_before = len(full_checks)
        clone.step(state, z[0], generator=torch.Generator().manual_seed(0))
        assert len(full_checks) == n_before + 1


def test_moving_the_filter_forgets_its_devices_and_its_states(full_checks):
    """The models' devices are remembered between calls (walking the module tree at every
    ``step`` was about a tenth of a step at B = 1) and forgotten when the filter moves: a state
    stepped before the move is checked in full, and models on another device are refused.
    """
    filt, x0, z = build()
    g = torch.Generator().manual_seed(1)
    state, _ = filt.step(filt.init(x0), z[0], generator=g)
    assert len(full_checks) == 1
    filt.to(torch.float64)  # a conversion (no-op here): the trusted states are forgotten
    state, _ = filt.step(state, z[1], generator=g)
    assert len(full_checks) == 2
    filt.to("meta")
    with pytest.raises(ValueError, match="the models' parameters are on meta, expected cpu"):
        filt.step(state, z[2], generator=g)
