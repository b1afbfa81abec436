"""agents.common.buffer.ReplayBuffer: samplers respect episode ends and the write head, GAE, truncation, state_dict."""
import pytest
import torch

from agents.common.buffer import ReplayBuffer

E = 2


def fill(rb: ReplayBuffer, rows: int, end_every=(3, 4), truncate_env=0):
    """Row g (global time) of env e holds obs = 100 g + e; env e's episodes end every end_every[e] rows (env
    ``truncate_env`` truncates, the other terminates); the final observation of an ended episode is -(100 g + e)."""
    for g in range(rows):
        obs = torch.tensor([100.0 * g + e for e in range(E)]).reshape(E, 1)
        ends = torch.tensor([(g + 1) % end_every[e] == 0 for e in range(E)])
        trunc = ends & (torch.arange(E) == truncate_env)
        term = ends & ~trunc
        rb.add({"x": obs}, torch.full((E, 3), float(g)), torch.full((E,), float(g)), term, trunc, final_obs={"x": -obs})
    return rb


def make(capacity=10, **kw):
    return ReplayBuffer(capacity, E, {"x": torch.zeros(E, 1)}, 3, **kw)


@pytest.mark.parametrize("rows", [7, 23, 24])       # before and after wrap-around
def test_uniform_next_obs_respects_episode_ends_and_head(rows):
    rb = fill(make(), rows)
    b = rb.sample(4000, generator=torch.Generator().manual_seed(0))
    obs, nxt = b["obs"]["x"][:, 0], b["next_obs"]["x"][:, 0]
    done = b["terminated"] | b["truncated"]
    assert torch.equal(nxt[done], -obs[done])                   # the stored final observation
    assert torch.equal(nxt[~done], obs[~done] + 100)            # the same env's next row, never another episode
    newest = 100 * (rows - 1)
    assert not ((obs >= newest) & ~done).any()                  # the head row has no next obs yet unless it ended
    assert (obs >= 100 * max(0, rows - 10)).all()               # overwritten rows are gone
    head_ended = sum((rows % k) == 0 for k in (3, 4))           # the newest row ended in these envs
    assert len(torch.unique(b["t"] * E + b["e"])) == (min(rows, 10) - 1) * E + head_ended   # all others reachable


@pytest.mark.parametrize("rows", [9, 23, 30])
def test_chunks_never_cross_episode_end_or_write_head(rows):
    rb = fill(make(), rows, end_every=(3, 5))
    b = rb.sample_sequences(500, 3, generator=torch.Generator().manual_seed(1))
    x = b["obs"]["x"][:, :-1, 0]                                # (batch, L): the rows, not the obs after them
    assert torch.equal(x[:, 1:] - x[:, :-1], torch.full_like(x[:, 1:], 100))   # contiguous in time, one env
    done = b["terminated"] | b["truncated"]
    assert not done[:, :-1].any()                               # an end only at the last row
    assert (x >= 100 * max(0, rows - 10)).all()                 # never the overwritten (or unwritten) side of the head
    # every valid chunk is found: with end_every 3 env 0 has chunks starting right after each end
    starts = {(int(t), int(e)) for t, e in rb.chunk_starts(3).tolist()}
    assert all(not bool((rb.terminated | rb.truncated)[(t + k) % 10, e]) for t, e in starts for k in range(2))
    with pytest.raises(ValueError):
        rb.sample_sequences(1, 6)                              # no 6-row chunk without an end in env 0


def test_gae_matches_hand_computation_and_bootstraps_truncation_only():
    gamma, lam = 0.9, 0.8
    rb = ReplayBuffer(3, 2, torch.zeros(2, 1), 1, store_value=True, store_log_prob=True)
    rewards = [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]
    values = [[0.5, 0.5], [0.4, 0.4], [0.3, 0.3]]
    for t in range(3):
        ended = torch.tensor([t == 1, t == 1])
        rb.add(torch.full((2, 1), float(t)), torch.zeros(2, 1), torch.tensor(rewards[t]),
               terminated=ended & torch.tensor([False, True]), truncated=ended & torch.tensor([True, False]),
               final_obs=torch.full((2, 1), 7.0), value=torch.tensor(values[t]), log_prob=torch.zeros(2))
    last_value = torch.tensor([0.7, 0.7])
    adv, ret = rb.compute_gae(last_value, gamma, lam, value_fn=lambda o: 10.0 * torch.ones(len(o)))
    # env 0 truncated at t=1: bootstraps V(final_obs) = 10; env 1 terminated at t=1: bootstraps 0.
    d2 = 3.0 + gamma * 0.7 - 0.3
    a2 = d2
    for env, boot in ((0, 10.0), (1, 0.0)):
        d1 = 2.0 + gamma * boot - 0.4
        a1 = d1                                                  # the episode ended: no trace from t=2
        d0 = 1.0 + gamma * 0.4 - 0.5
        a0 = d0 + gamma * lam * a1
        assert adv[:, env].tolist() == pytest.approx([a0, a1, a2], abs=1e-6)
        assert ret[:, env].tolist() == pytest.approx([a0 + 0.5, a1 + 0.4, a2 + 0.3], abs=1e-6)
    assert adv[1, 0] - adv[1, 1] == pytest.approx(gamma * 10.0)
    batches = list(rb.minibatches(4, generator=torch.Generator().manual_seed(0)))
    assert [len(b["advantage"]) for b in batches] == [4, 2]      # without replacement, every sample once
    seen = torch.cat([b["obs"][:, 0] * 10 + b["advantage"] for b in batches]).sort().values
    assert torch.allclose(seen, (torch.arange(3.0)[:, None] * 10 + adv).flatten().sort().values)


def test_state_dict_round_trip():
    rb = fill(make(), 23)
    other = make()
    other.load_state_dict(rb.state_dict())
    a = rb.sample(64, generator=torch.Generator().manual_seed(3))
    b = other.sample(64, generator=torch.Generator().manual_seed(3))
    for k in ("action", "reward", "terminated", "truncated"):
        assert torch.equal(a[k], b[k])
    assert torch.equal(a["obs"]["x"], b["obs"]["x"]) and torch.equal(a["next_obs"]["x"], b["next_obs"]["x"])
    assert other.pos == rb.pos and other.full == rb.full and other.final_obs.keys() == rb.final_obs.keys()
    partial = fill(make(), 4)                                    # not yet full: only written rows are saved
    again = make()
    again.load_state_dict(partial.state_dict())
    assert len(again) == 4 and torch.equal(again.obs["x"], partial.obs["x"])


def test_final_obs_required_and_uint8_kept():
    rb = ReplayBuffer(4, 1, {"image": torch.zeros(1, 8, 8, 3, dtype=torch.uint8)}, 2)
    assert rb.obs["image"].dtype == torch.uint8
    with pytest.raises(ValueError, match="final_obs"):
        rb.add({"image": torch.zeros(1, 8, 8, 3, dtype=torch.uint8)}, torch.zeros(1, 2), torch.zeros(1),
               torch.tensor([True]), torch.tensor([False]))


def test_a_buffer_that_never_wrapped_grows_when_loaded_into_a_larger_one():
    obs = {"p": torch.zeros(2, 3)}
    small = ReplayBuffer(4, 2, obs, 3)
    for i in range(3):
        small.add({"p": torch.full((2, 3), float(i))}, torch.zeros(2, 3), torch.full((2,), float(i)),
                  torch.zeros(2, dtype=torch.bool), torch.zeros(2, dtype=torch.bool))
    big = ReplayBuffer(10, 2, obs, 3)
    big.load_state_dict(small.state_dict())
    assert big.pos == 3 and len(big) == 3 and torch.equal(big.reward[:3], small.reward[:3])
    for i in range(3, 5):                                  # a full small buffer has wrapped: it cannot grow
        small.add({"p": torch.zeros(2, 3)}, torch.zeros(2, 3), torch.zeros(2), torch.zeros(2, dtype=torch.bool),
                  torch.zeros(2, dtype=torch.bool))
    with pytest.raises(ValueError, match="buffer shape mismatch"):
        ReplayBuffer(10, 2, obs, 3).load_state_dict(small.state_dict())
