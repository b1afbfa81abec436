"""One replay storage for every learner (SAC, PPO, PlaNet): time-major torch tensors ``[capacity, n_envs, ...]``.

Row ``t`` of env column ``e`` holds the transition taken from observation ``obs[t, e]``:
``action``, ``reward``, ``terminated``, ``truncated`` (+ optional ``log_prob`` and ``value``).

The next observation is NOT stored twice. It is ``obs[t + 1, e]`` unless the episode ended at row ``t``
(terminated or truncated): the env was then reset (our own autoreset) and ``obs[t + 1, e]`` is the first
observation of the next episode, so the TRUE final observation of the ended episode is kept in a small side table
``final_obs`` keyed by ``(t, e)`` (one entry per episode end, dropped when row ``t`` is overwritten). Bootstraps use
it: a truncated episode bootstraps from ``V(final_obs)`` / ``Q(final_obs, .)``; a terminated one never bootstraps.

Observations are dicts of tensors (a plain tensor is stored under the key ``"obs"``); uint8 images stay uint8.

Samplers:
- ``sample(batch)``: uniform transitions ``(obs, action, reward, next_obs, terminated, truncated)`` (SAC). The row
  just before the write head is excluded unless its episode ended there (its ``obs[t + 1]`` is not written yet).
- ``compute_gae`` + ``minibatches``: the latest rollout (the whole storage, filled once from row 0) with GAE(lambda)
  and shuffled minibatches without replacement (PPO).
- ``sample_sequences(batch, length)``: contiguous chunks of ``length`` rows of one env column that never cross an
  episode end (an end may only be the chunk's last row) nor the write head, plus the observation after the last row
  (PlaNet's world models).
"""
from __future__ import annotations

from typing import Any, Callable, Iterator

import torch

Obs = dict[str, torch.Tensor]


def as_dict(obs: Any) -> Obs:
    return obs if isinstance(obs, dict) else {"obs": obs}


def index_obs(obs: Obs, *idx) -> Obs:
    return {k: v[idx] for k, v in obs.items()}


class ReplayBuffer:
    def __init__(self, capacity: int, n_envs: int, obs_example: Any, action_dim: int, device: Any = "cpu",
                 store_log_prob: bool = False, store_value: bool = False):
        if capacity < 1 or n_envs < 1:
            raise ValueError(f"capacity and n_envs must be positive, got {capacity}, {n_envs}")
        self.capacity, self.n_envs, self.action_dim = int(capacity), int(n_envs), int(action_dim)
        self.device = torch.device(device)
        self.is_dict = isinstance(obs_example, dict)
        ex = as_dict(obs_example)
        c, e = self.capacity, self.n_envs
        self.obs = {k: torch.zeros((c, e, *v.shape[1:]), dtype=v.dtype, device=self.device) for k, v in ex.items()}
        self.action = torch.zeros(c, e, action_dim, device=self.device)
        self.reward = torch.zeros(c, e, device=self.device)
        self.terminated = torch.zeros(c, e, dtype=torch.bool, device=self.device)
        self.truncated = torch.zeros(c, e, dtype=torch.bool, device=self.device)
        self.log_prob = torch.zeros(c, e, device=self.device) if store_log_prob else None
        self.value = torch.zeros(c, e, device=self.device) if store_value else None
        self.final_obs: dict[tuple[int, int], Obs] = {}
        self.pos = 0          # write head: the next row to write
        self.full = False
        self.advantages: torch.Tensor | None = None
        self.returns: torch.Tensor | None = None

    # ------------------------------------------------------------------ writing
    def __len__(self) -> int:
        return self.capacity if self.full else self.pos

    @property
    def n_transitions(self) -> int:
        return len(self) * self.n_envs

    def add(self, obs: Any, action: torch.Tensor, reward: torch.Tensor, terminated: torch.Tensor,
            truncated: torch.Tensor, final_obs: Any = None, log_prob: torch.Tensor | None = None,
            value: torch.Tensor | None = None) -> None:
        """Write one row (all envs). ``final_obs``: the observation returned by the step (before any reset); only
        its rows where terminated | truncated are kept."""
        t = self.pos
        for k, v in as_dict(obs).items():
            self.obs[k][t] = v.to(self.device)
        self.action[t] = action.to(self.device, torch.float32)
        self.reward[t] = reward.to(self.device, torch.float32)
        self.terminated[t] = terminated.to(self.device)
        self.truncated[t] = truncated.to(self.device)
        if self.log_prob is not None and log_prob is not None:
            self.log_prob[t] = log_prob.to(self.device, torch.float32)
        if self.value is not None and value is not None:
            self.value[t] = value.to(self.device, torch.float32)
        for e in range(self.n_envs):
            self.final_obs.pop((t, e), None)
        done = (self.terminated[t] | self.truncated[t]).nonzero().flatten().tolist()
        if done:
            if final_obs is None:
                raise ValueError("final_obs is required on rows where an episode ends")
            fo = as_dict(final_obs)
            for e in done:
                self.final_obs[(t, e)] = {k: v[e].to(self.device).clone() for k, v in fo.items()}
        self.pos = (t + 1) % self.capacity
        self.full = self.full or self.pos == 0

    def reset(self) -> None:
        """Forget everything (PPO: start the next rollout at row 0)."""
        self.pos, self.full = 0, False
        self.final_obs.clear()
        self.advantages = self.returns = None

    # ------------------------------------------------------------------ helpers
    def _out(self, obs: Obs) -> Any:
        return obs if self.is_dict else obs["obs"]

    def next_obs(self, t: torch.Tensor, e: torch.Tensor) -> Obs:
        """Next observation of rows (t, e): obs[t + 1, e], or the stored final observation where the episode ended."""
        nxt = index_obs(self.obs, (t + 1) % self.capacity, e)
        done = (self.terminated[t, e] | self.truncated[t, e]).nonzero().flatten().tolist()
        for i in done:
            fo = self.final_obs[(int(t[i]), int(e[i]))]
            for k in nxt:
                nxt[k][i] = fo[k]
        return nxt

    def _valid_rows(self) -> torch.Tensor:
        """Mask (capacity, n_envs) of rows whose next observation is known."""
        valid = torch.zeros(self.capacity, self.n_envs, dtype=torch.bool, device=self.device)
        valid[: len(self)] = True
        last = (self.pos - 1) % self.capacity
        if len(self):
            valid[last] = self.terminated[last] | self.truncated[last]
        return valid

    # ------------------------------------------------------------------ SAC: uniform transitions
    def sample(self, batch_size: int, generator: torch.Generator | None = None) -> dict[str, Any]:
        """Uniform transitions: obs, action, reward, next_obs, terminated, truncated (each (batch, ...))."""
        flat = self._valid_rows().flatten().nonzero().flatten()
        if len(flat) == 0:
            raise ValueError("the buffer holds no complete transition yet")
        pick = flat[torch.randint(len(flat), (batch_size,), generator=generator, device="cpu").to(self.device)]
        t, e = pick // self.n_envs, pick % self.n_envs
        return {"obs": self._out(index_obs(self.obs, t, e)), "action": self.action[t, e],
                "reward": self.reward[t, e], "next_obs": self._out(self.next_obs(t, e)),
                "terminated": self.terminated[t, e], "truncated": self.truncated[t, e], "t": t, "e": e}

    # ------------------------------------------------------------------ PPO: latest rollout, GAE, minibatches
    def compute_gae(self, last_value: torch.Tensor, gamma: float, lam: float,
                    value_fn: Callable[[Any], torch.Tensor] | None = None,
                    final_values: dict[tuple[int, int], float] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """GAE(lambda) over rows [0, len) (a rollout written from row 0, no wrap-around).

        ``last_value`` (n_envs,): V of the observation after the last row. A terminated row bootstraps 0; a
        truncated row bootstraps V(final_obs), from ``final_values[(t, e)]`` or else ``value_fn`` applied to the
        stored final observations (batched). Returns (advantages, returns), each (T, n_envs), also kept here.
        """
        if self.value is None:
            raise ValueError("compute_gae needs a buffer built with store_value=True")
        if self.full and self.pos != 0:
            raise ValueError("compute_gae expects a rollout written from row 0 (call reset() before each rollout)")
        n = len(self)
        values = self.value[:n]
        boot = torch.zeros(n, self.n_envs, device=self.device)             # V(s_{t+1}) used by row t
        if n > 1:
            boot[:-1] = values[1:]
        boot[n - 1] = last_value.to(self.device, torch.float32)
        boot = torch.where(self.terminated[:n] | self.truncated[:n], torch.zeros_like(boot), boot)
        trunc = [(t, e) for (t, e) in self.final_obs if t < n and bool(self.truncated[t, e])]
        if trunc:
            if final_values is None:
                if value_fn is None:
                    raise ValueError("truncated rows need value_fn or final_values to bootstrap from final_obs")
                stacked = {k: torch.stack([self.final_obs[key][k] for key in trunc]) for k in self.obs}
                with torch.no_grad():
                    v = value_fn(self._out(stacked)).flatten().to(self.device, torch.float32)
                final_values = {key: v[i] for i, key in enumerate(trunc)}
            for key in trunc:
                boot[key] = float(final_values[key])
        done = (self.terminated[:n] | self.truncated[:n]).float()
        adv = torch.zeros(n, self.n_envs, device=self.device)
        last = torch.zeros(self.n_envs, device=self.device)
        for t in reversed(range(n)):
            delta = self.reward[t] + gamma * boot[t] - values[t]
            last = delta + gamma * lam * (1.0 - done[t]) * last
            adv[t] = last
        self.advantages, self.returns = adv, adv + values
        return self.advantages, self.returns

    def minibatches(self, batch_size: int, generator: torch.Generator | None = None) -> Iterator[dict[str, Any]]:
        """One epoch over the rollout in shuffled minibatches without replacement (after compute_gae)."""
        if self.advantages is None:
            raise ValueError("call compute_gae first")
        n = len(self) * self.n_envs
        perm = torch.randperm(n, generator=generator).to(self.device)
        for i in range(0, n, batch_size):
            idx = perm[i:i + batch_size]
            t, e = idx // self.n_envs, idx % self.n_envs
            out = {"obs": self._out(index_obs(self.obs, t, e)), "action": self.action[t, e],
                   "advantage": self.advantages[t, e], "return": self.returns[t, e]}
            if self.log_prob is not None:
                out["log_prob"] = self.log_prob[t, e]
            if self.value is not None:
                out["value"] = self.value[t, e]
            yield out

    # ------------------------------------------------------------------ PlaNet: contiguous chunks
    def chunk_starts(self, length: int) -> torch.Tensor:
        """All (start_row, env) pairs (K, 2) of valid chunks of ``length`` rows."""
        n = len(self)
        if length < 1 or length > n:
            return torch.zeros(0, 2, dtype=torch.int64)
        oldest = self.pos if self.full else 0
        ages = torch.arange(n - length + 1)                     # chunk start as an age (0 = oldest row)
        rows = (oldest + ages[:, None] + torch.arange(length)[None]) % self.capacity    # (S, L)
        ends = (self.terminated | self.truncated).cpu()[rows]   # (S, L, E)
        ok = ~ends[:, :-1].any(1)                               # an end only at the last row
        s, e = ok.nonzero(as_tuple=True)
        return torch.stack([rows[s, 0], e], dim=1)

    def sample_sequences(self, batch_size: int, length: int,
                         generator: torch.Generator | None = None) -> dict[str, Any]:
        """Uniform valid chunks (``chunk_starts``) and the observation after each one's last row: obs (batch,
        length + 1, ...), action (batch, length, A), reward, terminated, truncated, t, e (batch, length) and mask
        (batch, length + 1), 0 only for that extra observation where it is not written yet (the newest row, its
        episode not ended). The extra observation is ``next_obs``: the stored final one where the episode ended."""
        starts = self.chunk_starts(length)
        if len(starts) == 0:
            raise ValueError(f"no chunk of length {length} fits in the buffer yet")
        pick = starts[torch.randint(len(starts), (batch_size,), generator=generator)]
        t = ((pick[:, :1] + torch.arange(length)[None]) % self.capacity).to(self.device)   # (batch, L)
        e = pick[:, 1:].expand(-1, length).to(self.device)
        t_last, e_last = t[:, -1], e[:, -1]
        ended = self.terminated[t_last, e_last] | self.truncated[t_last, e_last]
        unknown = (t_last == (self.pos - 1) % self.capacity) & ~ended
        nxt = self.next_obs(t_last, e_last)
        obs = {k: torch.cat([v, nxt[k][:, None]], 1) for k, v in index_obs(self.obs, t, e).items()}
        mask = torch.ones(batch_size, length + 1, device=self.device)
        mask[:, -1] = (~unknown).float()
        return {"obs": self._out(obs), "action": self.action[t, e], "reward": self.reward[t, e],
                "terminated": self.terminated[t, e], "truncated": self.truncated[t, e], "mask": mask, "t": t, "e": e}

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        n = len(self)   # only written rows are saved (rows >= n are zeros)
        keys = sorted(self.final_obs)
        return {"capacity": self.capacity, "n_envs": self.n_envs, "pos": self.pos, "full": self.full,
                "obs": {k: v[:n].cpu().clone() for k, v in self.obs.items()},
                "action": self.action[:n].cpu().clone(), "reward": self.reward[:n].cpu().clone(),
                "terminated": self.terminated[:n].cpu().clone(), "truncated": self.truncated[:n].cpu().clone(),
                "log_prob": None if self.log_prob is None else self.log_prob[:n].cpu().clone(),
                "value": None if self.value is None else self.value[:n].cpu().clone(),
                "final_keys": torch.tensor(keys, dtype=torch.int64).reshape(-1, 2),
                "final_obs": {k: (torch.stack([self.final_obs[key][k].cpu() for key in keys]) if keys else None)
                              for k in self.obs}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Load a saved buffer of the same shape, or a smaller one that never wrapped around (a run resumed with a
        larger budget: its buffer, sized to the first budget, grows and its rows keep their places)."""
        grows = state["capacity"] < self.capacity and not state["full"]
        if (state["capacity"] != self.capacity and not grows) or state["n_envs"] != self.n_envs:
            raise ValueError(f"buffer shape mismatch: saved ({state['capacity']}, {state['n_envs']}), "
                             f"this ({self.capacity}, {self.n_envs})")
        n = state["action"].shape[0]
        for k, v in state["obs"].items():
            self.obs[k][:n] = v.to(self.device)
        for name in ("action", "reward", "terminated", "truncated", "log_prob", "value"):
            if state[name] is not None and getattr(self, name) is not None:
                getattr(self, name)[:n] = state[name].to(self.device)
        self.pos, self.full = int(state["pos"]), bool(state["full"])
        self.final_obs = {}
        for i, (t, e) in enumerate(state["final_keys"].tolist()):
            self.final_obs[(t, e)] = {k: v[i].to(self.device) for k, v in state["final_obs"].items()}
        self.advantages = self.returns = None
