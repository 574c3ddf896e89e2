import numpy as np
import pytest
import torch

import encoders
from encoders.testing import TINY_OPTIONS, random_obs
from quad_env.obs_layout import ObsLayout


def test_registered_names():
    assert set(encoders.ENCODERS) >= {"se3_graphormer", "se3_kattention", "graphormer", "kattention", "deepsets",
                                      "mlp", "infomarl"}  # the registry may grow, never lose one
    assert set(TINY_OPTIONS) == set(encoders.ENCODERS)
    assert encoders.resolve("se3_kattention") == ("kattention", "se3")
    assert encoders.resolve("se3_graphormer") == ("graphormer", "se3")
    assert encoders.resolve("deepsets") == ("deepsets", "none")
    assert encoders.resolve("deepsets", "yaw") == ("deepsets", "yaw")


def test_alias_with_another_symmetry_names_both():
    with pytest.raises(ValueError, match="se3_kattention.*'yaw'.*kattention"):
        encoders.resolve("se3_kattention", "yaw")
    with pytest.raises(ValueError, match="symmetry 'so2'.*none.*se3.*yaw"):
        encoders.make_encoder("deepsets", ObsLayout(), symmetry="so2")
    with pytest.raises(ValueError, match="size preset 'huge'.*paper.*small"):
        encoders.make_encoder("deepsets", ObsLayout(), size="huge")


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_small_preset_is_smaller_and_kwargs_override_it(name):
    layout = ObsLayout(6)
    count = lambda m: sum(p.numel() for p in m.parameters())  # noqa: E731
    small, paper = (encoders.make_encoder(name, layout, size=s) for s in ("small", "paper"))
    assert count(small) * 5 < count(paper)
    assert small.out_dim == 64
    wider = encoders.make_encoder(name, layout, size="small", **({"zeta_sizes": (64, 64, 64, 96)}
                                                                  if "graphormer" in name else {"out_dim": 96}))
    assert wider.out_dim == 96


def test_unknown_name_lists_valid_names():
    with pytest.raises(ValueError) as err:
        encoders.make_encoder("transformer", ObsLayout())
    for name in encoders.ENCODERS:
        assert name in str(err.value)


@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_unknown_option_is_named(name):
    with pytest.raises(TypeError, match="hiden"):
        encoders.make_encoder(name, ObsLayout(), hiden=3)


def test_bad_layout_and_obs_shape():
    with pytest.raises(TypeError, match="ObsLayout"):
        encoders.make_encoder("deepsets", {"num_neighbors": 6})
    enc = encoders.make_encoder("deepsets", ObsLayout(3), **TINY_OPTIONS["deepsets"])
    with pytest.raises(ValueError, match="expects"):
        enc(torch.zeros(2, ObsLayout(4).dim))


def test_bad_sizes_are_errors():
    with pytest.raises(ValueError, match="out_vectors"):
        encoders.make_encoder("se3_kattention", ObsLayout(), out_dim=32, out_vectors=11)
    with pytest.raises(ValueError, match="num_heads"):
        encoders.make_encoder("se3_graphormer", ObsLayout(), multiplicity=3, num_heads=5)
    with pytest.raises(ValueError, match="activation"):
        encoders.make_encoder("deepsets", ObsLayout(), activation="sigmoidish")


@pytest.mark.parametrize("layout", [ObsLayout(6), ObsLayout(2, "pos_vel", True), ObsLayout(0)], ids=repr)
@pytest.mark.parametrize("name", encoders.ENCODERS)
def test_output_shape_and_declared_representation(name, layout):
    enc = encoders.make_encoder(name, layout, **TINY_OPTIONS[name])
    out = enc(torch.as_tensor(random_obs(layout, 5, np.random.default_rng(0)), dtype=torch.float32))
    assert out.shape == (5, enc.out_dim) and out.dtype == torch.float32
    assert torch.isfinite(out).all()
    if encoders.resolve(name)[1] != "none":
        scalars, vectors = enc.equivariance
        assert scalars + 3 * vectors == enc.out_dim and vectors > 0
    else:
        assert enc.equivariance is None


def test_options_reach_the_module():
    opts = encoders.encoder_options("se3_graphormer")
    assert opts["multiplicity"] == 60 and opts["num_layers"] == 3  # paper sizes by default
    enc = encoders.make_encoder("se3_graphormer", ObsLayout(), multiplicity=5, num_layers=2, out_vectors=10)
    assert len(enc.layers) == 2 and enc.layers[0].width == 20 and enc.equivariance == (256 - 30, 10)
