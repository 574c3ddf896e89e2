"""Learning: V-trace-corrected APPO on fragments from the rollout workers.

Read top to bottom: ``Learner.train(fragments)`` stacks fragments into one time-major batch,
then for every epoch and every minibatch of whole trajectories (columns) it
recomputes values with the current critic, folds truncation bootstraps into the rewards,
runs V-trace, and takes one clipped-surrogate step. Steps whose policy lag exceeds
``algo.max_policy_lag`` are masked out of every loss and statistic.
"""
from __future__ import annotations

import warnings
from typing import Any, Dict, List, Tuple

import numpy as np
import torch

from swarm_appo.config import COMPILE_MODES
from swarm_appo.losses import appo_loss
from swarm_appo.metrics import LagStats
from swarm_appo.precision import autocast
from swarm_appo.vtrace import fold_truncation_bootstrap, vtrace
from swarm_appo.weight_ema import STATE_KEY as EMA_KEY
from swarm_appo.weight_ema import WeightEMA


def stack_fragments(fragments: List[Dict[str, Any]]) -> Dict[str, np.ndarray]:
    """Concatenate fragments along the trajectory axis B -> one batch ``[T, sum B, ...]``."""
    out: Dict[str, Any] = {}
    for key in ("obs", "actions", "log_probs", "values", "rewards", "terminated", "truncated"):
        out[key] = np.concatenate([f[key] for f in fragments], axis=1)
    out["last_obs"] = np.concatenate([f["last_obs"] for f in fragments], axis=0)  # [B, D]
    if all("rnn_state" in f for f in fragments):
        out["rnn_state"] = np.concatenate([f["rnn_state"] for f in fragments], axis=0)  # [B, S]
    versions, final_obs, final_idx, col = [], [], [], 0
    for f in fragments:
        T, B = f["rewards"].shape
        versions.append(np.broadcast_to(f["policy_version"][:, None], (T, B)))
        final_obs.append(f["final_obs"])
        final_idx.append(f["final_idx"] + np.array([0, col]))
        col += B
    out["policy_version"] = np.concatenate(versions, axis=1)  # [T, B]
    out["final_obs"] = np.concatenate(final_obs)  # [M, D]
    out["final_idx"] = np.concatenate(final_idx)  # [M, 2] (t, b)
    sizes = {f.get("num_agents") for f in fragments}
    if len(sizes) > 1:
        raise ValueError(f"fragments of different swarm sizes {sorted(sizes, key=str)} cannot share a batch")
    out["num_agents"] = sizes.pop()  # N (None from fragments that do not say)
    return out


def swarm_members(cols: torch.Tensor, num_agents: int) -> torch.Tensor:
    """Columns of every drone in the swarm of each column: ``[b] -> [b, N]`` (swarm e = columns e*N .. e*N+N-1)."""
    first = torch.div(cols, num_agents, rounding_mode="floor") * num_agents
    return first[:, None] + torch.arange(num_agents, device=cols.device)


class Learner:
    """Owns the model being trained, its optimizer and the policy version counter."""

    def __init__(self, model: torch.nn.Module, algo, device: torch.device, seed: int, precision: str = "fp32",
                 compile: str = "off"):
        self.algo = algo
        self.device = device
        self.precision = precision  # "fp32" | "bf16" (resolved): the forward passes run under autocast
        self.model = model.to(device)
        # runner.compile: the training forward compiled (the bound method, so state_dict keys are unchanged)
        if compile not in COMPILE_MODES:
            raise ValueError(f"unknown compile mode {compile!r}; valid: {list(COMPILE_MODES)}")
        self._evaluate_sequence = (self.model.evaluate_sequence if compile == "off"
                                   else torch.compile(self.model.evaluate_sequence, mode=compile))
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=algo.lr, betas=tuple(algo.adam_betas),
                                          eps=algo.adam_eps)
        self.generator = torch.Generator().manual_seed(seed)
        self.version = 0  # bumped once per train() call; published with the weights
        self.num_updates = 0  # optimizer steps taken
        self.skipped_updates = 0  # non-finite loss or gradient
        self.consecutive_skips = 0  # skipped updates since the last good one (the trainer stops a run at a limit)
        self._num_agents = None  # drones per swarm of the batch in training (a central critic needs it)
        # algo.weight_ema: running averages of the weights, a read-out for choosing the final policy
        self.weight_ema = WeightEMA(self.model, algo.weight_ema) if algo.weight_ema else None

    # ------------------------------------------------------------------ weights
    def cpu_weights(self) -> Tuple[int, Dict[str, torch.Tensor]]:
        return self.version, {k: v.detach().to("cpu", copy=True) for k, v in self.model.state_dict().items()}

    def state_dict(self) -> Dict[str, Any]:
        state = {"model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
                 "version": self.version, "num_updates": self.num_updates,
                 "skipped_updates": self.skipped_updates, "generator": self.generator.get_state()}
        if self.weight_ema is not None:
            state[EMA_KEY] = self.weight_ema.state_dict()
        return state

    def load_state_dict(self, state: Dict[str, Any]) -> None:
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.version = state["version"]
        self.num_updates = state["num_updates"]
        self.skipped_updates = state.get("skipped_updates", 0)
        self.generator.set_state(state["generator"])
        if self.weight_ema is not None:
            if EMA_KEY in state:
                self.weight_ema.load_state_dict(state[EMA_KEY])
            else:  # a checkpoint of a run without algo.weight_ema: the averages start at the resumed weights
                warnings.warn("the checkpoint holds no weight EMA (algo.weight_ema): the averages start now")
                self.weight_ema = WeightEMA(self.model, self.weight_ema.horizons)

    # ------------------------------------------------------------------ training
    def train(self, fragments: List[Dict[str, Any]]) -> Dict[str, float]:
        algo, dev = self.algo, self.device
        t, lag, valid = self._to_tensors(fragments)
        T, B = t["rewards"].shape
        lag_stats = LagStats()
        lag_stats.update(lag, max_policy_lag=algo.max_policy_lag)
        obs_norm = getattr(self.model, "obs_norm", None)
        if obs_norm is not None:  # statistics move once per batch, before the epochs (Sample Factory style)
            obs_norm.update(t["obs"][valid])

        cols_per_mb = max(1, algo.batch_size // T)
        stats_sum: Dict[str, float] = {}
        n_mb = 0
        self.model.train()
        for _epoch in range(algo.num_epochs):
            perm = torch.randperm(B, generator=self.generator).to(dev)
            for start in range(0, B, cols_per_mb):
                cols = perm[start:start + cols_per_mb]  # [b]
                stats = self._minibatch_step(t, cols, valid[:, cols], t["final_idx"])
                if stats is None:
                    continue
                for k, v in stats.items():
                    stats_sum[k] = stats_sum.get(k, 0.0) + v
                n_mb += 1
        self.version += 1
        if self.weight_ema is not None:
            self.weight_ema.update(self.model, T * B)
        out = {f"losses/{k}": v / max(n_mb, 1) for k, v in stats_sum.items()}
        out.update(lag_stats.summary())
        out.update({"losses/skipped_updates": float(self.skipped_updates),
                    "perf/policy_version": float(self.version), "perf/num_updates": float(self.num_updates)})
        return out

    def _to_tensors(self, fragments: List[Dict[str, Any]]):
        batch = stack_fragments(fragments)
        self._num_agents = batch.pop("num_agents")
        if getattr(self.model, "central", False) and self._num_agents is None:
            raise ValueError("model.critic=central needs fragments that name their swarm size (num_agents)")
        t = {k: torch.as_tensor(v, device=self.device) for k, v in batch.items()}
        if getattr(self.model, "central", False):  # row of final_obs per truncated (t, b), once per batch
            fi = t["final_idx"]
            t["final_row"] = torch.full(t["rewards"].shape, -1, dtype=torch.long, device=fi.device)  # [T, B]
            t["final_row"][fi[:, 0], fi[:, 1]] = torch.arange(fi.shape[0], device=fi.device)
        lag = self.version - t["policy_version"]  # [T, B] learner version - behaviour version
        valid = lag <= self.algo.max_policy_lag  # [T, B]
        return t, lag, valid

    @torch.no_grad()
    def loss_on(self, fragments: List[Dict[str, Any]]) -> float:
        """The APPO loss of the current model on these fragments (all columns at once), no update."""
        t, _, valid = self._to_tensors(fragments)
        cols = torch.arange(t["rewards"].shape[1], device=self.device)
        loss, _ = self._loss(t, cols, valid, t["final_idx"])
        return float(loss)

    def _loss(self, t: Dict[str, torch.Tensor], cols: torch.Tensor, valid: torch.Tensor,
              final_idx: torch.Tensor):
        """APPO loss on the whole trajectories ``cols``: values and V-trace targets from the current model."""
        algo = self.algo
        obs = t["obs"][:, cols]  # [T, b, D]
        T, b, D = obs.shape
        actions = t["actions"][:, cols]  # [T, b, A]
        old_logp = t["log_probs"][:, cols]  # [T, b]
        # a central critic sees each drone's whole swarm, read from the batch's own observations
        members = swarm_members(cols, self._num_agents) if getattr(self.model, "central", False) else None  # [b, N]
        swarm = None if members is None else t["obs"][:, members]  # [T, b, N, D]
        # a recurrent core unrolls from the state stored with the fragment, reset where an episode begins
        recurrent = bool(getattr(self.model, "state_size", 0))
        done = t["terminated"][:, cols] | t["truncated"][:, cols]  # [T, b]
        state0 = t["rnn_state"][cols] if recurrent else None  # [b, S]
        starts = torch.cat([torch.zeros_like(done[:1]), done[:-1]]) if recurrent else None  # [T, b]
        with autocast(self.precision, self.device):  # bf16 matmuls; the model returns fp32 means and values
            log_prob, entropy, values, states = self._evaluate_sequence(obs, actions, state0, starts, swarm)

        with torch.no_grad(), autocast(self.precision, self.device):
            last_swarm = None if members is None else t["last_obs"][members]  # [b, N, D]
            # the state that reaches last_obs: after step T-1, reset if that step ended an episode
            last_state = None if states is None else torch.where(done[-1, :, None], 0.0, states[-1])  # [b, S]
            bootstrap = self.model.get_value(t["last_obs"][cols], last_swarm, last_state)  # [b]
            # Truncated steps bootstrap from the value of the true final observation, not the reset one (with
            # a core: from the state after that step, the one that reached the final observation).
            col_pos = torch.full((t["rewards"].shape[1],), -1, dtype=torch.long, device=obs.device)
            col_pos[cols] = torch.arange(b, device=obs.device)
            final_values = torch.zeros(T, b, device=obs.device)  # [T, b]
            if final_idx.shape[0]:
                sel = col_pos[final_idx[:, 1]] >= 0
                if sel.any():
                    fi = final_idx[sel]
                    pos = col_pos[fi[:, 1]]
                    final_values[fi[:, 0], pos] = self.model.get_value(
                        t["final_obs"][sel], None if members is None else self._final_swarm(t, fi),
                        None if states is None else states[fi[:, 0], pos])
            discounts = algo.gamma * (~t["terminated"][:, cols]).float()  # [T, b]
            rewards, discounts = fold_truncation_bootstrap(
                t["rewards"][:, cols], discounts, t["truncated"][:, cols], final_values, algo.gamma)
            vt = vtrace(log_prob.detach() - old_logp, discounts, rewards, values.detach(), bootstrap,
                        clip_rho_threshold=algo.vtrace_rho_clip, clip_c_threshold=algo.vtrace_c_clip,
                        clip_pg_rho_threshold=algo.vtrace_pg_rho_clip, lambda_=algo.vtrace_lambda)

        return appo_loss(
            log_prob.reshape(-1), old_logp.reshape(-1), vt.pg_advantages.reshape(-1), values.reshape(-1),
            vt.vs.reshape(-1), entropy.reshape(-1), valid.reshape(-1).float(),
            clip_ratio=algo.ppo_clip_ratio, value_coeff=algo.value_loss_coeff, entropy_coeff=algo.entropy_coeff,
            old_values=t["values"][:, cols].reshape(-1), value_clip=algo.value_clip,
            normalize_advantages=algo.normalize_advantages)

    def _final_swarm(self, t: Dict[str, torch.Tensor], fi: torch.Tensor) -> torch.Tensor:
        """The true final observations of every drone in the swarm of each truncated step ``fi`` [m, 2] (t, col):
        ``[m, N, D]``. A swarm's episode ends for all its drones at once, so each member has a final row."""
        rows = t["final_row"][fi[:, :1], swarm_members(fi[:, 1], self._num_agents)]  # [m, N]
        if (rows < 0).any():
            raise ValueError("a truncated step whose swarm mates have no final observation: fragments must hold "
                             "whole swarms")
        return t["final_obs"][rows]

    def _minibatch_step(self, t: Dict[str, torch.Tensor], cols: torch.Tensor, valid: torch.Tensor,
                        final_idx: torch.Tensor):
        loss, stats = self._loss(t, cols, valid, final_idx)
        if not torch.isfinite(loss):
            self.skipped_updates += 1
            self.consecutive_skips += 1
            warnings.warn(f"non-finite loss ({loss.item()}) at update {self.num_updates}: update skipped")
            return None
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.algo.max_grad_norm)
        if not torch.isfinite(grad_norm):
            self.optimizer.zero_grad(set_to_none=True)
            self.skipped_updates += 1
            self.consecutive_skips += 1
            warnings.warn(f"non-finite gradient norm at update {self.num_updates}: update skipped")
            return None
        self.optimizer.step()
        self.num_updates += 1
        self.consecutive_skips = 0
        # valid_fraction is lag/masked_fraction's complement (logged by LagStats): not logged twice
        stats = {k: float(v) for k, v in stats.items() if k != "valid_fraction"}
        stats["grad_norm"] = float(grad_norm)
        return stats
