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
from typing import Optional

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
    """

    def __init__(self, layout: ObsLayout, encoder: str = "deepsets", encoder_kwargs: Optional[dict] = None,
                 share_encoder: bool = False, action_dim: int = 4, head_hidden: Optional[int] = None,
                 head_activation: str = "tanh", init_log_std: float = 0.0, normalize_obs: bool = False,
                 init_action_mean: float = 0.0, init_actor_out_scale: float = 1.0,
                 body_frame_obs: Optional[bool] = False,
                 symmetry: Optional[str] = None, size: str = "paper", critic: str = "local"):
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
        head_hidden = HEAD_HIDDEN[size] if head_hidden is None else head_hidden
        self.layout = layout
        self.symmetry = symmetry
        self.config = dict(encoder=encoder, encoder_kwargs=encoder_kwargs, symmetry=symmetry, size=size,
                           share_encoder=share_encoder,
                           action_dim=action_dim, head_hidden=head_hidden, head_activation=head_activation,
                           init_log_std=init_log_std, normalize_obs=normalize_obs,
                           init_action_mean=init_action_mean, init_actor_out_scale=init_actor_out_scale,
                           body_frame_obs=body_frame_obs, critic=critic)
        self.share_encoder = share_encoder
        self.action_dim = action_dim
        self.obs_norm = FieldScaleNorm(layout) if normalize_obs else None
        self.body_frame = BodyFrameInput(layout) if body_frame_obs else None
        self.actor_encoder = make_encoder(encoder, layout, symmetry, size, **encoder_kwargs)
        self.critic_encoder = None if share_encoder else make_encoder(encoder, layout, symmetry, size, **encoder_kwargs)
        out_dim = self.actor_encoder.out_dim
        self.central = critic == "central"
        # central critic: phi(own-state block) per drone of the swarm, averaged; its width follows the heads'
        state_width = head_hidden or HEAD_HIDDEN[size]
        self.swarm_state = xavier_init_(mlp([layout.self_dim, state_width, state_width], head_activation)) \
            if self.central else None
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

    def _swarm_features(self, features: torch.Tensor, swarm_obs: Optional[torch.Tensor]) -> torch.Tensor:
        """The critic's input: ``features`` [B, F], with a central critic followed by the swarm's pooled state."""
        if not self.central:
            return features
        if swarm_obs is None:
            raise ValueError("critic='central' needs swarm_obs [B, N, D] (every drone of the drone's swarm; "
                             "encoders.actor_critic.swarm_observations builds it from swarm-ordered rows)")
        B, N, D = swarm_obs.shape
        own = self._normalize(swarm_obs.reshape(B * N, D))[:, :self.layout.self_dim]  # [B*N, S]
        pooled = self.swarm_state(own).reshape(B, N, -1).mean(1)  # [B, W]: invariant to the drones' order
        return torch.cat([features, pooled.to(features.dtype)], dim=-1)

    def _features(self, obs: torch.Tensor, swarm_obs: Optional[torch.Tensor] = None):
        obs = self._normalize(obs)
        actor = self.actor_encoder(obs)  # [B, out_dim]
        critic = actor if self.critic_encoder is None else self.critic_encoder(obs)
        return actor, self._swarm_features(critic, swarm_obs)

    def get_value(self, obs: torch.Tensor, swarm_obs: Optional[torch.Tensor] = None) -> torch.Tensor:
        """V(obs): [B] (a central critic also needs ``swarm_obs`` [B, N, D])."""
        encoder = self.actor_encoder if self.critic_encoder is None else self.critic_encoder
        features = self._swarm_features(encoder(self._normalize(obs)), swarm_obs)
        return self.critic_head(features).squeeze(-1).to(self.log_std.dtype)

    def policy(self, obs: torch.Tensor):
        """``(mean [B, A], log_std [A])`` without the critic: what acting needs."""
        return self.actor_head(self.actor_encoder(self._normalize(obs))).to(self.log_std.dtype), self.log_std

    def forward(self, obs: torch.Tensor, swarm_obs: Optional[torch.Tensor] = None):
        """``(mean [B, A], log_std [A], value [B])`` in the parameters' dtype: under bf16 autocast
        (``runner.precision``) the log-probs, ratios and value targets computed from them stay float32.
        ``swarm_obs`` [B, N, D]: the swarm of each drone, for a central critic (ignored by a local one)."""
        actor, critic = self._features(obs, swarm_obs)
        dtype = self.log_std.dtype
        return self.actor_head(actor).to(dtype), self.log_std, self.critic_head(critic).squeeze(-1).to(dtype)

    # ------------------------------------------------------------------ RL interface
    def act(self, obs: torch.Tensor, deterministic: bool = False, generator: Optional[torch.Generator] = None,
            with_value: bool = True, swarm_obs: Optional[torch.Tensor] = None):
        """Sample (or take the mean of) the unclipped Gaussian: ``(actions [B, A], log_prob [B], value [B])``.

        The one definition of acting, for rollout workers (sampling), evaluation (the mean, or a seeded sample)
        and tests. ``with_value=False`` skips the critic (about half the cost of acting) and returns zeros for
        the value. The noise is ``torch.randn(mean.shape, generator=generator)``: one draw per action entry."""
        if with_value:
            mean, log_std, value = self(obs, swarm_obs)
        else:
            (mean, log_std), value = self.policy(obs), obs.new_zeros(obs.shape[0], dtype=self.log_std.dtype)
        if deterministic:
            actions = mean
        else:
            noise = torch.randn(mean.shape, generator=generator, dtype=mean.dtype, device=mean.device)
            actions = mean + noise * torch.exp(log_std)
        return actions, gaussian_log_prob(mean, log_std, actions), value

    def evaluate(self, obs: torch.Tensor, actions: torch.Tensor, swarm_obs: Optional[torch.Tensor] = None):
        """``(log_prob [B], entropy [B], value [B])`` of given actions."""
        mean, log_std, value = self(obs, swarm_obs)
        entropy = (0.5 + HALF_LOG_2PI + log_std).sum().expand(mean.shape[0])
        return gaussian_log_prob(mean, log_std, actions), entropy, value
