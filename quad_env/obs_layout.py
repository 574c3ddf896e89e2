"""The observation layout: the one contract between the environment and the encoders.

A drone's observation is a flat float32 vector of ``layout.dim`` entries:

    [ self block (18) | K neighbour blocks (21 each, or 6 with ``pos_vel``) | K mask entries | obstacle field ]

Every field has a name, a slice into the flat vector and an SE(3) *kind* that says how it
transforms when the whole world is moved by a global rotation Q and translation t:

- ``world_vector``: a 3-vector in world axes; becomes ``Q v`` (all positions are relative, so t drops out).
- ``rotation``: a 3x3 body->world rotation stored row-major; becomes ``Q R``.
- ``body``: expressed in the drone's own body frame; unchanged.
- ``scalar``: an invariant number; unchanged.
- ``mask``: 1.0 where the neighbour slot holds a real neighbour, 0.0 for padding; unchanged.

Neighbour fields are laid out neighbour-major (all fields of neighbour 0, then neighbour 1, ...),
sorted by distance (nearest first). Encoders and tests must read observations only through this
object (``split`` / ``transform``), never through hard-coded offsets.

Works on numpy arrays and torch tensors alike (only slicing, reshape and matmul are used).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Tuple

FIELD_KINDS = ("world_vector", "rotation", "body", "scalar", "mask")
NEIGHBOR_OBS_TYPES = ("full", "pos_vel")

# (name, size, kind) of the drone's own state.
SELF_FIELDS: Tuple[Tuple[str, int, str], ...] = (
    ("rel_goal", 3, "world_vector"),  # x_i - x_i^d
    ("vel", 3, "world_vector"),  # v_i
    ("rot", 9, "rotation"),  # R_i, body -> world, row-major
    ("omega", 3, "body"),  # body rates
)
# (name, size, kind) of one neighbour j, relative to drone i.
NEIGHBOR_FIELDS: Dict[str, Tuple[Tuple[str, int, str], ...]] = {
    "full": (
        ("rel_pos", 3, "world_vector"),  # x_j - x_i
        ("rel_vel", 3, "world_vector"),  # v_j - v_i
        ("rot", 9, "rotation"),  # R_j
        ("omega", 3, "body"),  # omega_j (in j's body frame)
        ("goal_offset", 3, "world_vector"),  # x_j^d - x_j
    ),
    "pos_vel": (
        ("rel_pos", 3, "world_vector"),
        ("rel_vel", 3, "world_vector"),
    ),
}
# Signed distances (m) from the points (x + (a - 1) 0.1, y + (b - 1) 0.1), entry 3 a + b, around the drone's
# (x, y) to the nearest obstacle surface, clipped to env.obstacle_sdf_max. Kind "scalar": unchanged by
# ``transform``. (The 3x3 grid is aligned with the world axes, so strictly the field is invariant to
# translations only; rotations about z by quarter turns permute its entries, which ``transform`` ignores.)
OBSTACLE_FIELD = ("obstacle_sdf", 9, "scalar")


@dataclass(frozen=True)
class Field:
    name: str
    start: int  # first index in the flat vector (for neighbour fields: within neighbour 0)
    size: int
    kind: str
    group: str  # "self" | "neighbor" | "mask" | "obstacle"

    @property
    def stop(self) -> int:
        return self.start + self.size


class ObsLayout:
    """Names, slices and SE(3) kinds of every observation entry.

    Args:
        num_neighbors: K, the number of neighbour slots (K >= 0).
        neighbor_obs: "full" (paper: 21 per neighbour) or "pos_vel" (QuadSwarm baseline: 6).
        obstacle_obs: whether the 9-entry obstacle field is appended.
    """

    def __init__(self, num_neighbors: int = 6, neighbor_obs: str = "full", obstacle_obs: bool = False):
        if not isinstance(num_neighbors, int) or num_neighbors < 0:
            raise ValueError(f"num_neighbors must be an int >= 0, got {num_neighbors!r}")
        if neighbor_obs not in NEIGHBOR_FIELDS:
            raise ValueError(f"unknown neighbor_obs {neighbor_obs!r}; valid: {list(NEIGHBOR_FIELDS)}")
        self.num_neighbors = num_neighbors
        self.neighbor_obs = neighbor_obs
        self.obstacle_obs = bool(obstacle_obs)

        fields: List[Field] = []
        pos = 0
        for name, size, kind in SELF_FIELDS:
            fields.append(Field(name, pos, size, kind, "self"))
            pos += size
        self.self_dim = pos
        self.neighbor_start = pos
        npos = 0
        for name, size, kind in NEIGHBOR_FIELDS[neighbor_obs]:
            fields.append(Field(name, pos + npos, size, kind, "neighbor"))
            npos += size
        self.neighbor_dim = npos
        pos += npos * num_neighbors
        self.mask_start = pos
        fields.append(Field("mask", pos, num_neighbors, "mask", "mask"))
        pos += num_neighbors
        if self.obstacle_obs:
            name, size, kind = OBSTACLE_FIELD
            fields.append(Field(name, pos, size, kind, "obstacle"))
            pos += size
        self.dim = pos
        self.fields: Tuple[Field, ...] = tuple(fields)

    # ------------------------------------------------------------------ queries
    def field(self, name: str, group: str = "self") -> Field:
        for f in self.fields:
            if f.name == name and f.group == group:
                return f
        valid = [f"{f.group}.{f.name}" for f in self.fields]
        raise KeyError(f"no field {group}.{name}; valid: {valid}")

    def fields_of(self, group: str) -> Tuple[Field, ...]:
        return tuple(f for f in self.fields if f.group == group)

    def __repr__(self) -> str:
        return (f"ObsLayout(num_neighbors={self.num_neighbors}, neighbor_obs={self.neighbor_obs!r}, "
                f"obstacle_obs={self.obstacle_obs}, dim={self.dim})")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ObsLayout) and (self.num_neighbors, self.neighbor_obs, self.obstacle_obs) == (
            other.num_neighbors, other.neighbor_obs, other.obstacle_obs)

    def __hash__(self) -> int:
        return hash((self.num_neighbors, self.neighbor_obs, self.obstacle_obs))

    def to_dict(self) -> Dict[str, Any]:
        return {"num_neighbors": self.num_neighbors, "neighbor_obs": self.neighbor_obs,
                "obstacle_obs": self.obstacle_obs}

    @classmethod
    def from_dict(cls, d: Dict[str, Any]) -> "ObsLayout":
        return cls(**d)

    # ------------------------------------------------------------------ views
    def neighbors(self, obs):
        """All neighbour blocks as ``[..., K, neighbor_dim]``."""
        k = self.num_neighbors
        block = obs[..., self.neighbor_start:self.neighbor_start + k * self.neighbor_dim]
        return block.reshape(*obs.shape[:-1], k, self.neighbor_dim)

    def split(self, obs) -> Dict[str, Any]:
        """Split a batch ``[..., D]`` into named fields.

        Returns keys ``self.<name>`` -> ``[..., size]``, ``neighbor.<name>`` -> ``[..., K, size]``,
        ``mask`` -> ``[..., K]`` and, if present, ``obstacle.<name>`` -> ``[..., size]``.
        Rotation fields keep their flat 9 entries; use ``as_matrix`` for ``[..., 3, 3]``.
        """
        if obs.shape[-1] != self.dim:
            raise ValueError(f"observation has {obs.shape[-1]} entries, layout {self!r} expects {self.dim}")
        out: Dict[str, Any] = {}
        nb = self.neighbors(obs)
        for f in self.fields:
            if f.group == "neighbor":
                off = f.start - self.neighbor_start
                out[f"neighbor.{f.name}"] = nb[..., off:off + f.size]
            elif f.group == "mask":
                out["mask"] = obs[..., f.start:f.stop]
            else:
                out[f"{f.group}.{f.name}"] = obs[..., f.start:f.stop]
        return out

    @staticmethod
    def as_matrix(flat_rot):
        """``[..., 9]`` row-major -> ``[..., 3, 3]``."""
        return flat_rot.reshape(*flat_rot.shape[:-1], 3, 3)

    # ------------------------------------------------------------------ group action
    def transform(self, obs, Q):
        """Observation of the same world moved by a global rotation ``Q`` (3x3) and any translation.

        World vectors become ``Q v``, rotations ``Q R``; body fields, scalars and masks are unchanged.
        (Every position in the observation is relative, so translations leave it invariant.)
        ``obs`` is ``[..., D]`` (numpy or torch); ``Q`` is a matrix of the same library and dtype.
        """
        if obs.shape[-1] != self.dim:
            raise ValueError(f"observation has {obs.shape[-1]} entries, layout {self!r} expects {self.dim}")
        out = obs.copy() if hasattr(obs, "copy") and not hasattr(obs, "clone") else obs.clone()
        Qt = Q.T if hasattr(Q, "T") else Q.transpose(-1, -2)
        blocks = [(0, f) for f in self.fields if f.group in ("self", "obstacle")]
        for k in range(self.num_neighbors):
            blocks += [(k * self.neighbor_dim, f) for f in self.fields if f.group == "neighbor"]
        for off, f in blocks:
            s = slice(f.start + off, f.stop + off)
            if f.kind == "world_vector":
                out[..., s] = obs[..., s] @ Qt
            elif f.kind == "rotation":
                R = obs[..., s].reshape(*obs.shape[:-1], 3, 3)
                out[..., s] = (Q @ R).reshape(*obs.shape[:-1], 9)
        return out
