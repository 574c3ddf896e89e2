"""Neighbour encoders (Graphormer, K-Attention, DeepSets, MLP), each with a symmetry (none, se3, yaw), and the
actor-critic.

    enc = make_encoder("se3_graphormer", layout, multiplicity=16)   # obs [B, D] -> [B, enc.out_dim]
    enc = make_encoder("deepsets", layout, symmetry="yaw", size="small")
    model = ActorCritic(layout, encoder="deepsets")
"""
from .actor_critic import CORES, CRITICS, ActorCritic, swarm_observations
from .frames import SYMMETRIES
from .registry import ALIASES, ARCHITECTURES, ENCODERS, SIZES, encoder_options, make_encoder, resolve

__all__ = ["ActorCritic", "CORES", "CRITICS", "ALIASES", "ARCHITECTURES", "ENCODERS", "SIZES", "SYMMETRIES",
           "encoder_options", "make_encoder", "resolve", "swarm_observations"]
