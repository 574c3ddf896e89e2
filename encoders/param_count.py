"""Print the parameter count of every encoder (paper sizes) and of the actor-critic built on it.

    python -m encoders.param_count [--num-neighbors 6] [--neighbor-obs full] [--obstacle-obs]
"""
from __future__ import annotations

import argparse

from quad_env.obs_layout import NEIGHBOR_FIELDS, ObsLayout

from .actor_critic import ActorCritic
from .registry import ENCODERS, make_encoder


def count(module) -> int:
    return sum(p.numel() for p in module.parameters())


def table(layout: ObsLayout) -> str:
    header = (f"{'encoder':<15} {'out_dim':>7} {'representation':>14} {'encoder':>11} {'actor-critic':>13} "
              f"{'(shared)':>11}")
    lines = [f"parameters for {layout!r}", header, "-" * len(header)]
    for name in ENCODERS:
        enc = make_encoder(name, layout)
        rep = "-" if enc.equivariance is None else "%d s + %d v" % enc.equivariance
        lines.append(f"{name:<15} {enc.out_dim:>7} {rep:>14} {count(enc):>11,} "
                     f"{count(ActorCritic(layout, encoder=name)):>13,} "
                     f"{count(ActorCritic(layout, encoder=name, share_encoder=True)):>11,}")
    return "\n".join(lines)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-neighbors", type=int, default=6, help="K, neighbour slots")
    parser.add_argument("--neighbor-obs", default="full", choices=list(NEIGHBOR_FIELDS))
    parser.add_argument("--obstacle-obs", action="store_true", help="append the obstacle field")
    args = parser.parse_args(argv)
    print(table(ObsLayout(args.num_neighbors, args.neighbor_obs, args.obstacle_obs)))


if __name__ == "__main__":
    main()
