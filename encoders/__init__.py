"""Neighbour encoders (SE(3)-Graphormer, SE(3)-K-Attention, K-Attention, DeepSets, MLP) and the actor-critic.

    enc = make_encoder("se3_graphormer", layout, multiplicity=16)   # obs [B, D] -> [B, enc.out_dim]
    model = ActorCritic(layout, encoder="deepsets")
"""
from .actor_critic import ActorCritic
from .registry import ENCODER_CLASSES, ENCODERS, encoder_options, make_encoder

__all__ = ["ActorCritic", "ENCODERS", "ENCODER_CLASSES", "encoder_options", "make_encoder"]
