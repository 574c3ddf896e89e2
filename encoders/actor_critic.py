"""Actor-critic of paper section 6: pi(u | s, o) = h_p(pi_hat(s, o)), a diagonal Gaussian.

pi_hat is any registered encoder (for the SE(3) ones: the equivariant part, whose output is in world
axes); h_p is a plain MLP [(out_dim, 256), (256, action_dim)] giving the Gaussian's mean, with a learned
state-independent log-std. Because h_p sees the equivariant features in world axes, the policy as a whole
is not equivariant -- which it must not be, as gravity breaks the symmetry of the dynamics. The critic has
the same structure ([(out_dim, 256), (256, 1)]) and its own encoder unless ``share_encoder``.

With ``critic="central"`` (MAPPO's centralised value function) the critic also sees its swarm's global state:
every drone's own-state block (position relative to its goal, velocity, rotation, body rates: the first
``layout.self_dim`` entries of its observation), embedded drone by drone and averaged (a DeepSets over the swarm,
so the critic is invariant to the drones' order), concatenated to the critic encoder's output. The actor never
sees it: acting, evaluation and export need the drone's own observation only, for any swarm size.
"""
from __future__ import annotations

import math
from typing import List, Optional, Tuple

import torch
from torch import nn

from quad_env.obs_layout import ObsLayout

from .body_frame import BodyFrameInput
from .common import mlp, xavier_init_
from .obs_norm import FieldScaleNorm
from .registry import make_encoder, resolve
from .symmetric import Canonicalized

HEAD_HIDDEN = {"paper": 256, "small": 64}  # head width per model.size preset

HALF_LOG_2PI = 0.5 * math.log(2.0 * math.pi)
CRITICS = ("local", "central")  # model.critic: the agent's observation only | + the swarm's global state
CORES = ("none", "gru", "lstm")  # model.core: feed-forward | a recurrent cell between encoder and head


class RecurrentCore(nn.Module):
    """One GRU or LSTM cell with a flat state: ``(x [B, I], state [B, S]) -> (y [B, H], state' [B, S])``,
    S = H for a GRU and 2H for an LSTM (h | c). The state keeps its own dtype (fp32 under bf16 autocast)."""

    def __init__(self, kind: str, in_dim: int, size: int):
        super().__init__()
        self.kind, self.size = kind, size
        self.cell = nn.GRUCell(in_dim, size) if kind == "gru" else nn.LSTMCell(in_dim, size)
        self.state_size = size if kind == "gru" else 2 * size

    def forward(self, x: torch.Tensor, state: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        if self.kind == "gru":
            h = self.cell(x, state.to(x.dtype))
            return h, h.to(state.dtype)
        h, c = self.cell(x, (state[:, :self.size].to(x.dtype), state[:, self.size:].to(x.dtype)))
        return h, torch.cat([h, c], dim=-1).to(state.dtype)


def swarm_observations(obs: torch.Tensor, num_agents: int) -> torch.Tensor:
    """Every drone's view of its whole swarm, ``[B, D] -> [B, N, D]``, for drones stored swarm by swarm
    (rows e*N .. e*N+N-1 are swarm e, the layout of ``VecQuadEnv`` and of a fragment's columns). A view, no copy."""
    B, D = obs.shape
    if num_agents < 1 or B % num_agents:
        raise ValueError(f"{B} drones are not whole swarms of {num_agents}")
    E = B // num_agents
    return obs.view(E, 1, num_agents, D).expand(E, num_agents, num_agents, D).reshape(B, num_agents, D)


def gaussian_log_prob(mean: torch.Tensor, log_std: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Log-density of a diagonal Gaussian, summed over the action dim: [B, A] -> [B]."""
    z = (actions - mean) * torch.exp(-log_std)
    return (-0.5 * z.pow(2) - log_std - HALF_LOG_2PI).sum(-1)


class ActorCritic(nn.Module):
    """Gaussian policy and value function on top of a named encoder.

    Args:
        layout: observation layout.
        encoder: registered encoder name (see ``encoders.ENCODERS``).
        encoder_kwargs: options passed to the encoder, over its size preset (e.g. ``{"multiplicity": 16}``).
        symmetry: the encoder's symmetry group, "none" | "se3" | "yaw" (None: the encoder name's own).
        size: size preset of the encoder and the heads, "paper" | "small".
        share_encoder: actor and critic use one encoder (the paper: separate weights, the default).
        action_dim: size of the action (4 rotor commands).
        head_hidden: hidden width of the actor and critic heads; None = the size preset's (paper 256, small 64);
            0 = linear heads (one Linear from the encoder output, as Sample Factory's action and value heads).
        head_activation: nonlinearity of the heads.
        init_log_std: initial value of the learned log standard deviation.
        normalize_obs: scale each observation field by its running RMS norm first (``FieldScaleNorm``,
            equivariance-preserving); its statistics change only through ``obs_norm.update``.
        init_action_mean: initial mean action (the bias of the actor's last layer), e.g. the hover command.
        body_frame_obs: feed the network the observation in the drone's body frame (``BodyFrameInput``); only
            with symmetry "none" (a symmetric encoder canonicalizes its inputs itself). None = auto: on for
            symmetry "none", off otherwise.
        init_actor_out_scale: multiplies the Xavier-uniform weights of the actor's last layer; small values
            (PPO practice: 0.01) start the policy at a near-constant mean action ``init_action_mean``.
        critic: "local" (the critic sees what the actor sees) or "central" (plus the swarm's global state,
            passed as ``swarm_obs [B, N, D]`` to every method that computes values; see the module docstring).
        core: "none" (feed-forward, the paper), "gru" or "lstm": a recurrent cell between encoder and head, for
            the actor and (with its own cell unless ``share_encoder``) the critic. Its state ``[B, state_size]``
            (actor | critic; zeros at an episode start) goes in and out of ``act``; the learner unrolls whole
            trajectories with ``evaluate_sequence``.
        core_size: hidden size of each cell; None = the heads' width (paper 256, small 64).
    """

    def __init__(self, layout: ObsLayout, encoder: str = "deepsets", encoder_kwargs: Optional[dict] = None,
                 share_encoder: bool = False, action_dim: int = 4, head_hidden: Optional[int] = None,
                 head_activation: str = "tanh", init_log_std: float = 0.0, normalize_obs: bool = False,
                 init_action_mean: float = 0.0, init_actor_out_scale: float = 1.0,
                 body_frame_obs: Optional[bool] = False,
                 symmetry: Optional[str] = None, size: str = "paper", critic: str = "local",
                 core: str = "none", core_size: Optional[int] = None):
        super().__init__()
        encoder_kwargs = dict(encoder_kwargs or {})
        _, symmetry = resolve(encoder, symmetry)
        if body_frame_obs is None:  # auto: body-frame inputs through the symmetry if there is one, else the aid
            body_frame_obs = symmetry == "none"
        if body_frame_obs and symmetry != "none":
            raise ValueError(f"body_frame_obs=True rotates the inputs into the body frame, which symmetry "
                             f"{symmetry!r} (encoder {encoder!r}) does itself: set body_frame_obs=False or "
                             f"symmetry='none'")
        if critic not in CRITICS:
            raise ValueError(f"unknown critic {critic!r}; valid: {list(CRITICS)}")
        if size not in HEAD_HIDDEN:
            raise ValueError(f"unknown size preset {size!r}; valid: {list(HEAD_HIDDEN)}")
        if core not in CORES:
            raise ValueError(f"unknown core {core!r}; valid: {list(CORES)}")
        if core_size is not None and core_size < 1:
            raise ValueError(f"core_size must be >= 1 or None, got {core_size}")
        head_hidden = HEAD_HIDDEN[size] if head_hidden is None else head_hidden
        self.layout = layout
        self.symmetry = symmetry
        self.config = dict(encoder=encoder, encoder_kwargs=encoder_kwargs, symmetry=symmetry, size=size,
                           share_encoder=share_encoder,
                           action_dim=action_dim, head_hidden=head_hidden, head_activation=head_activation,
                           init_log_std=init_log_std, normalize_obs=normalize_obs,
                           init_action_mean=init_action_mean, init_actor_out_scale=init_actor_out_scale,
                           body_frame_obs=body_frame_obs, critic=critic, core=core, core_size=core_size)
        self.share_encoder = share_encoder
        self.action_dim = action_dim
        self.obs_norm = FieldScaleNorm(layout) if normalize_obs else None
        self.body_frame = BodyFrameInput(layout) if body_frame_obs else None
        self.actor_encoder = make_encoder(encoder, layout, symmetry, size, **encoder_kwargs)
        self.critic_encoder = None if share_encoder else make_encoder(encoder, layout, symmetry, size, **encoder_kwargs)
        # separate actor and critic encoders canonicalized alike read one copy of the frame-mapped observation
        self.one_frame_map = (isinstance(self.actor_encoder, Canonicalized)
                              and isinstance(self.critic_encoder, Canonicalized)
                              and self.actor_encoder.symmetry == self.critic_encoder.symmetry)
        out_dim = self.actor_encoder.out_dim
        self.central = critic == "central"
        # central critic: phi(own-state block) per drone of the swarm, averaged; its width follows the heads'
        state_width = head_hidden or HEAD_HIDDEN[size]
        self.swarm_state = xavier_init_(mlp([layout.self_dim, state_width, state_width], head_activation)) \
            if self.central else None
        # recurrent core: encoder -> cell -> head; the critic has its own cell unless it shares the encoder
        self.actor_core = self.critic_core = None
        if core != "none":
            size_h = core_size or head_hidden or HEAD_HIDDEN[size]
            self.actor_core = RecurrentCore(core, out_dim, size_h)
            self.critic_core = None if share_encoder else RecurrentCore(core, out_dim, size_h)
            out_dim = size_h
        self.state_sizes = tuple(c.state_size if c is not None else 0 for c in (self.actor_core, self.critic_core))
        self.state_size = sum(self.state_sizes)  # 0: feed-forward
        critic_in = out_dim + (state_width if self.central else 0)
        hidden = [head_hidden] if head_hidden else []  # 0: linear heads (Sample Factory's, for like-for-like runs)
        self.actor_head = xavier_init_(mlp([out_dim, *hidden, action_dim], head_activation, last_act=False))
        self.critic_head = xavier_init_(mlp([critic_in, *hidden, 1], head_activation, last_act=False))
        with torch.no_grad():
            self.actor_head[-1].bias.fill_(float(init_action_mean))
            self.actor_head[-1].weight.mul_(float(init_actor_out_scale))
        self.log_std = nn.Parameter(torch.full((action_dim,), float(init_log_std)))

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """``nn.Module.load_state_dict``, also reading checkpoints from before the symmetry option (their
        se3_kattention weights sat at ``<encoder>.net.*``, now ``<encoder>.inner.net.*``)."""
        state_dict = dict(state_dict)
        for name in ("actor_encoder", "critic_encoder"):
            if not isinstance(getattr(self, name), Canonicalized):
                continue
            old, new = f"{name}.net.", f"{name}.inner.net."
            for key in [k for k in state_dict if k.startswith(old)]:
                state_dict[new + key[len(old):]] = state_dict.pop(key)
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    # ------------------------------------------------------------------ pieces
    def _normalize(self, obs: torch.Tensor) -> torch.Tensor:
        # The per-field scales are norms, which a rotation into the body frame leaves unchanged.
        if self.body_frame is not None:
            obs = self.body_frame(obs)
        return obs if self.obs_norm is None else self.obs_norm(obs)

    @staticmethod
    def _encode(encoder: nn.Module, x: torch.Tensor, canonical) -> torch.Tensor:
        """``encoder(x)``, or from the frame-mapped copy ``canonical`` (``Canonicalized.canonical``) if given."""
        return encoder(x) if canonical is None else encoder(x, canonical)

    def _swarm_features(self, features: torch.Tensor, swarm_obs: Optional[torch.Tensor]) -> torch.Tensor:
        """The critic head's input: ``features`` [B, F], with a central critic followed by the swarm's pooled
        state."""
        if not self.central:
            return features
        if swarm_obs is None:
            raise ValueError("critic='central' needs swarm_obs [B, N, D] (every drone of the drone's swarm; "
                             "encoders.actor_critic.swarm_observations builds it from swarm-ordered rows)")
        B, N, D = swarm_obs.shape
        own = self._normalize(swarm_obs.reshape(B * N, D))[:, :self.layout.self_dim]  # [B*N, S]
        pooled = self.swarm_state(own).reshape(B, N, -1).mean(1)  # [B, W]: invariant to the drones' order
        return torch.cat([features, pooled.to(features.dtype)], dim=-1)

    def initial_state(self, batch: int, device=None) -> torch.Tensor:
        """The core state at an episode start: zeros ``[batch, state_size]`` (``[batch, 0]`` feed-forward)."""
        return torch.zeros(batch, self.state_size, dtype=self.log_std.dtype, device=device)

    def _check_state(self, state: Optional[torch.Tensor], batch: int) -> Tuple[torch.Tensor, torch.Tensor]:
        """``state`` [B, S] split into (actor, critic) parts; a feed-forward model takes None."""
        if state is None:
            if self.state_size:
                raise ValueError(f"core={self.config['core']!r} needs the core state [B, {self.state_size}] "
                                 f"(model.initial_state(B) at an episode start)")
            state = self.log_std.new_zeros(batch, 0)
        elif state.shape != (batch, self.state_size):
            raise ValueError(f"core state has shape {tuple(state.shape)}, expected ({batch}, {self.state_size})")
        return state[:, :self.state_sizes[0]], state[:, self.state_sizes[0]:]

    def _step(self, obs: torch.Tensor, state: Optional[torch.Tensor], swarm_obs: Optional[torch.Tensor],
              actor: bool = True, critic: bool = True):
        """One control step: ``(mean [B, A] or None, value [B] or None, state' [B, S])``. A recurrent critic
        cell always runs: its state must advance whether or not the value is wanted."""
        a_state, c_state = self._check_state(state, obs.shape[0])
        x = self._normalize(obs)
        dtype = self.log_std.dtype
        shared = self.critic_encoder is None
        mean = value = None
        run_actor = actor or (critic and shared) or self.actor_core is not None
        run_critic = critic or self.critic_core is not None
        canonical = self.actor_encoder.canonical(x) if self.one_frame_map and run_actor and run_critic else None
        if run_actor:
            a = self._encode(self.actor_encoder, x, canonical)  # [B, out]
            if self.actor_core is not None:
                a, a_state = self.actor_core(a, a_state)
            if actor:
                mean = self.actor_head(a).to(dtype)
        if run_critic:
            c = a if shared else self._encode(self.critic_encoder, x, canonical)
            if self.critic_core is not None:
                c, c_state = self.critic_core(c, c_state)
            if critic:
                value = self.critic_head(self._swarm_features(c, swarm_obs)).squeeze(-1).to(dtype)
        return mean, value, torch.cat([a_state, c_state], dim=-1)

    def get_value(self, obs: torch.Tensor, swarm_obs: Optional[torch.Tensor] = None,
                  state: Optional[torch.Tensor] = None) -> torch.Tensor:
        """V(obs): [B] (a central critic also needs ``swarm_obs`` [B, N, D], a recurrent one the core
        ``state`` before this step)."""
        return self._step(obs, state, swarm_obs, actor=False)[1]

    def policy(self, obs: torch.Tensor, state: Optional[torch.Tensor] = None):
        """``(mean [B, A], log_std [A])`` without the critic: what acting needs (feed-forward models)."""
        return self._step(obs, state, None, critic=False)[0], self.log_std

    def forward(self, obs: torch.Tensor, swarm_obs: Optional[torch.Tensor] = None,
                state: Optional[torch.Tensor] = None):
        """``(mean [B, A], log_std [A], value [B])`` in the parameters' dtype: under bf16 autocast
        (``runner.precision``) the log-probs, ratios and value targets computed from them stay float32.
        ``swarm_obs`` [B, N, D]: the swarm of each drone, for a central critic (ignored by a local one)."""
        mean, value, _ = self._step(obs, state, swarm_obs)
        return mean, self.log_std, value

    # ------------------------------------------------------------------ RL interface
    def act(self, obs: torch.Tensor, deterministic: bool = False, generator: Optional[torch.Generator] = None,
            with_value: bool = True, swarm_obs: Optional[torch.Tensor] = None, state: Optional[torch.Tensor] = None):
        """Sample (or take the mean of) the unclipped Gaussian: ``(actions [B, A], log_prob [B], value [B])``,
        and with ``state`` (the core state before this step, ``[B, state_size]``) a fourth output, the state
        after it.

        The one definition of acting, for rollout workers (sampling), evaluation (the mean, or a seeded sample)
        and tests. ``with_value=False`` skips the critic (about half the cost of acting; a recurrent critic cell
        still runs) and returns zeros for the value. The noise is ``torch.randn(mean.shape, generator=generator)``:
        one draw per action entry."""
        mean, value, new_state = self._step(obs, state, swarm_obs, critic=with_value)
        if value is None:
            value = obs.new_zeros(obs.shape[0], dtype=self.log_std.dtype)
        log_std = self.log_std
        if deterministic:
            actions = mean
        else:
            noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
            actions = mean + noise * torch.exp(log_std)
        out = (actions, gaussian_log_prob(mean, log_std, actions), value)
        return out if state is None else (*out, new_state)

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor, swarm_obs: Optional[torch.Tensor] = None):
        """``(log_prob [B], entropy [B], value [B])`` of given actions (feed-forward models)."""
        mean, log_std, value = self(obs, swarm_obs)
        entropy = (0.5 + HALF_LOG_2PI + log_std).sum().expand(mean.shape[0])
        return gaussian_log_prob(mean, log_std, actions), entropy, value

    def evaluate_sequence(self, obs: torch.Tensor, actions: torch.Tensor, state: Optional[torch.Tensor] = None,
                          starts: Optional[torch.Tensor] = None, swarm_obs: Optional[torch.Tensor] = None):
        """The learner's view of whole trajectories: ``obs [T, b, D]``, ``actions [T, b, A]``; for a recurrent
        model also the core ``state [b, S]`` before step 0 and ``starts [T, b]`` (True where an episode begins:
        the state is reset to zeros before that step); ``swarm_obs [T, b, N, D]`` for a central critic.

        Returns ``(log_prob [T, b], entropy [T, b], value [T, b], states)``, ``states [T, b, S]`` the core state
        after each step, before any reset (None feed-forward): the bootstrap of a truncated step reads its true
        final observation with it. The encoders run once on all T*b rows; only the cells step through time."""
        T, b, D = obs.shape
        swarm = None if swarm_obs is None else swarm_obs.reshape(T * b, *swarm_obs.shape[2:])
        if not self.state_size:
            log_prob, entropy, value = self.evaluate(obs.reshape(T * b, D), actions.reshape(T * b, -1), swarm)
            return log_prob.reshape(T, b), entropy.reshape(T, b), value.reshape(T, b), None
        a_state, c_state = self._check_state(state, b)
        x = self._normalize(obs.reshape(T * b, D))
        a_in = self.actor_encoder(x).reshape(T, b, -1)
        c_in = None if self.critic_encoder is None else self.critic_encoder(x).reshape(T, b, -1)
        keep = torch.ones(T, b, 1, dtype=torch.bool, device=obs.device) if starts is None else ~starts[..., None]
        a_out: List[torch.Tensor] = []
        c_out: List[torch.Tensor] = []
        states: List[torch.Tensor] = []
        for t in range(T):
            a_state = torch.where(keep[t], a_state, torch.zeros_like(a_state))
            c_state = torch.where(keep[t], c_state, torch.zeros_like(c_state))
            y, a_state = self.actor_core(a_in[t], a_state)
            a_out.append(y)
            if self.critic_core is not None:
                y, c_state = self.critic_core(c_in[t], c_state)
                c_out.append(y)
            states.append(torch.cat([a_state, c_state], dim=-1))
        a = torch.stack(a_out).reshape(T * b, -1)
        c = a if self.critic_core is None else torch.stack(c_out).reshape(T * b, -1)
        dtype = self.log_std.dtype
        mean = self.actor_head(a).to(dtype)
        value = self.critic_head(self._swarm_features(c, swarm)).squeeze(-1).to(dtype)
        log_prob = gaussian_log_prob(mean, self.log_std, actions.reshape(T * b, -1))
        entropy = (0.5 + HALF_LOG_2PI + self.log_std).sum().expand(T * b)
        return log_prob.reshape(T, b), entropy.reshape(T, b), value.reshape(T, b), torch.stack(states)
