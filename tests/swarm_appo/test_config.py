"""Config tree: defaults, YAML files, overrides, strict errors, save/load round trip, validation."""
import ast
import inspect
from pathlib import Path

import pytest
import yaml

import swarm_appo.config as config_module
from quad_env.config import EnvConfig
from swarm_appo.config import (AlgoConfig, ConfigError, TrainConfig, config_from_dict, config_to_dict,
                               default_config, load_config, parse_override, save_config, validate)

REPO_ROOT = Path(__file__).resolve().parents[2]
QUICKSTART_YAML = str(REPO_ROOT / "configs" / "quickstart.yaml")
PAPER_YAML = str(REPO_ROOT / "configs" / "paper.yaml")


def test_algorithm_defaults_are_the_papers():
    a = AlgoConfig()
    assert (a.lr, a.gamma, a.adam_betas, a.adam_eps, a.max_grad_norm) == (1e-4, 0.99, (0.9, 0.995), 2e-6, 5.0)
    assert (a.rollout, a.batch_size, a.num_epochs) == (128, 4096, 5)
    assert a.value_clip is None
    cfg = TrainConfig()
    assert isinstance(cfg.env, EnvConfig) and cfg.model.encoder == "deepsets" and cfg.wandb.mode == "offline"
    assert cfg.wandb.project == "swarm-appo" and cfg.runner.run_dir == "runs" and cfg.runner.device == "auto"


def test_paper_yaml_is_appendix_iii():
    cfg = load_config(PAPER_YAML)
    a = cfg.algo
    assert a.lr == 1e-4 and a.gamma == 0.99 and a.adam_betas == (0.9, 0.995) and a.adam_eps == 2e-6
    assert a.max_grad_norm == 5.0 and a.rollout == 128 and a.batch_size == 4096 and a.num_epochs == 5
    # not in the paper: what its training code ran with (Sample Factory's default clip, QuadSwarm's commands)
    assert a.ppo_clip_ratio == 0.1 and a.value_clip == 5.0 and a.entropy_coeff == 0.0
    assert cfg.model.encoder == "se3_graphormer" and cfg.model.head_activation == "tanh"
    assert cfg.env.num_agents == 8


def test_quickstart_yaml_equals_the_embedded_default():
    embedded = load_config(None)
    assert load_config(QUICKSTART_YAML) == embedded == default_config()
    assert embedded.algo.batch_size % embedded.algo.rollout == 0 and embedded.env.num_agents == 8
    assert embedded.algo.batch_size < AlgoConfig().batch_size  # it is the small setting


def test_every_field_has_a_docstring():
    tree = ast.parse(inspect.getsource(config_module))
    classes = {n.name: n for n in tree.body if isinstance(n, ast.ClassDef)}
    for cls in (config_module.ModelConfig, config_module.AlgoConfig, config_module.RunnerConfig,
                config_module.WandbConfig, config_module.TrainConfig):
        body = classes[cls.__name__].body
        for i, node in enumerate(body):
            if isinstance(node, ast.AnnAssign):
                nxt = body[i + 1] if i + 1 < len(body) else None
                documented = isinstance(nxt, ast.Expr) and isinstance(getattr(nxt, "value", None), ast.Constant)
                assert documented, f"{cls.__name__}.{node.target.id} has no docstring"


@pytest.mark.parametrize("text, key, value", [
    ("env.num_agents=16", "env.num_agents", 16),
    ("algo.lr=1e-4", "algo.lr", 1e-4),
    ("algo.lr=3.0e-4", "algo.lr", 3e-4),
    ("runner.serial=true", "runner.serial", True),
    ("algo.value_clip=null", "algo.value_clip", None),
    ("algo.adam_betas=[0.9, 0.99]", "algo.adam_betas", [0.9, 0.99]),
    ("model.encoder_kwargs={multiplicity: 16}", "model.encoder_kwargs", {"multiplicity": 16}),
    ("model.encoder=se3_graphormer", "model.encoder", "se3_graphormer"),
    ("runner.name=a=b", "runner.name", "a=b"),
])
def test_parse_override_reads_yaml_values(text, key, value):
    assert parse_override(text) == (key, value)


@pytest.mark.parametrize("text", ["env.num_agents", "=3", "env..num_agents=3", "env.=3"])
def test_malformed_overrides_are_errors(text):
    with pytest.raises(ConfigError, match="override"):
        parse_override(text)


def test_overrides_apply_with_types():
    cfg = load_config(None, ["env.num_agents=16", "algo.lr=1e-3", "algo.adam_betas=[0.8, 0.9]",
                             "env.reward.pos=1", "runner.total_agent_steps=5e6", "wandb.tags=[a, b]",
                             "model.encoder_kwargs.out_dim=32", "env.sensing_radius=2"])
    assert cfg.env.num_agents == 16 and cfg.algo.lr == 1e-3 and cfg.algo.adam_betas == (0.8, 0.9)
    assert cfg.env.reward.pos == 1.0 and isinstance(cfg.env.reward.pos, float)
    assert cfg.runner.total_agent_steps == 5_000_000 and isinstance(cfg.runner.total_agent_steps, int)
    assert cfg.wandb.tags == ("a", "b")
    assert cfg.model.encoder_kwargs == {"out_dim": 32} and cfg.model.size == "small"  # over the quickstart preset
    assert cfg.env.sensing_radius == 2.0
    # Later overrides win; the other fields keep the file's values.
    cfg = load_config(PAPER_YAML, ["algo.lr=1e-3", "algo.lr=2e-3"])
    assert cfg.algo.lr == 2e-3 and cfg.algo.batch_size == 4096


@pytest.mark.parametrize("override, fragments", [
    ("algo.lrr=1", ["'algo.lrr'", "did you mean 'algo.lr'", "'adam_betas'", "'vtrace_c_clip'"]),
    ("env.reward.poss=1", ["'env.reward.poss'", "valid keys in 'env.reward'", "'proximity_dist'"]),
    ("env.physics.masss=1", ["'env.physics.masss'", "'mass'"]),
    ("foo.bar=1", ["'foo'", "top level", "'runner'", "'wandb'"]),
    ("algo.lr.x=2", ["'algo.lr' is a value, not a section"]),
])
def test_unknown_keys_name_the_dotted_key_and_the_valid_ones(override, fragments):
    with pytest.raises(ConfigError) as info:
        load_config(None, [override])
    for fragment in fragments:
        assert fragment in str(info.value)


@pytest.mark.parametrize("override, fragments", [
    ("algo.lr=abc", ["'algo.lr'", "float", "'abc'"]),
    ("env.num_agents=2.5", ["'env.num_agents'", "int", "2.5"]),
    ("env.num_agents=true", ["'env.num_agents'", "int", "True"]),
    ("runner.serial=1", ["'runner.serial'", "bool", "1"]),
    ("algo.value_clip=yes", ["'algo.value_clip'", "Optional[float]", "'yes'"]),
    ("runner.serial=on", ["'runner.serial'", "bool", "'on'"]),  # YAML 1.1's on/off/yes/no are words here
    ("algo.adam_betas=[0.9]", ["'algo.adam_betas'", "2 values", "[0.9]"]),
    ("algo.adam_betas=0.9", ["'algo.adam_betas'", "Tuple[float, float]"]),
    ("model.encoder_kwargs=3", ["'model.encoder_kwargs'", "Dict"]),
    ("wandb.tags=[1]", ["'wandb.tags[0]'", "str"]),
    ("env.physics.inertia=[1, 2]", ["'env.physics.inertia'", "3 values"]),
    ("env.reward=5", ["'env.reward'", "mapping"]),
])
def test_wrong_types_name_key_expected_type_and_value(override, fragments):
    with pytest.raises(ConfigError) as info:
        load_config(None, [override])
    for fragment in fragments:
        assert fragment in str(info.value), (fragment, str(info.value))


def test_yaml_1_1_words_are_strings_and_only_true_false_are_booleans(tmp_path):
    # runner.compile's mode "off" must not turn into False (YAML 1.1 reads off/on/yes/no as booleans)
    assert load_config(None, ["runner.compile=off"]).runner.compile == "off"
    path = tmp_path / "c.yaml"
    path.write_text("runner:\n  compile: off\n  serial: true\nwandb:\n  mode: disabled\n")
    cfg = load_config(str(path))
    assert cfg.runner.compile == "off" and cfg.runner.serial is True
    assert load_config(None, ["runner.serial=FALSE"]).runner.serial is False


@pytest.mark.parametrize("override, fragment", [
    ("algo.batch_size=1000", "algo.batch_size (1000) must be a multiple of algo.rollout (128)"),
    ("algo.gamma=1.5", "algo.gamma"),
    ("algo.lr=0", "algo.lr"),
    ("algo.adam_betas=[0.9, 1.0]", "algo.adam_betas"),
    ("algo.value_clip=-1", "algo.value_clip"),
    ("algo.vtrace_c_clip=0", "algo.vtrace_c_clip"),
    ("runner.device=tpu", "runner.device"),
    ("wandb.mode=sometimes", "wandb.mode must be one of ['offline', 'online', 'disabled']"),
    ("runner.name=a/b", "runner.name"),
    ("runner.keep_checkpoints=0", "runner.keep_checkpoints"),
    ("env.num_agents=0", "env.num_agents"),
    ("env.neighbor_obs=radar", "env.neighbor_obs"),
])
def test_out_of_range_values_are_errors_naming_the_key(override, fragment):
    with pytest.raises(ConfigError) as info:
        load_config(None, [override])
    assert fragment in str(info.value)


def test_inconsistent_worker_settings():
    with pytest.raises(ConfigError, match="max_fragments_in_flight.*num_workers"):
        load_config(None, ["runner.num_workers=4", "runner.max_fragments_in_flight=2"])
    assert load_config(None, ["runner.num_workers=4", "runner.max_fragments_in_flight=4"]).runner.num_workers == 4
    assert load_config(None, ["runner.device=cuda:1"]).runner.device == "cuda:1"


@pytest.mark.parametrize("overrides,message", [
    (["model.encoder=transformer"], r"model.encoder: unknown encoder 'transformer'.*valid: \['se3_graphormer'"),
    (["env.scenario=statc_same_goal"], r"env.scenario: unknown scenario 'statc_same_goal' \(did you mean "
                                       r"'static_same_goal'\?\); valid: \["),
    (["env.scenario=o_random"], r"env.scenario='o_random' flies through obstacles: set env.obstacles=true"),
    (["env.scenario=swarm_vs_swarm", "env.num_agents=1"], r"env.scenario='swarm_vs_swarm' needs env.num_agents >= 2"),
    (["model.symmetry=so2"], r"model.symmetry must be one of \['none', 'se3', 'yaw'\]"),
    (["model.size=huge"], r"model.size must be one of \['paper', 'small'\]"),
    (["model.encoder=se3_kattention", "model.body_frame_obs=false", "model.symmetry=yaw"],
     r"model.encoder='se3_kattention' and model.symmetry='yaw' contradict"),
    (["model.encoder=se3_graphormer", "model.body_frame_obs=true"],
     r"model.body_frame_obs=true and model.symmetry='se3'"),
    (["model.symmetry=yaw", "model.body_frame_obs=true"], r"model.body_frame_obs=true and model.symmetry='yaw'"),
    (["model.encoder=graphormer", "model.body_frame_obs=false", "model.encoder_kwargs.hidden=8"],
     r"model.encoder_kwargs.*unknown option\(s\) \['hidden'\]"),
    (["model.encoder_kwargs.hidden=0"], r"model.encoder_kwargs"),
    (["model.encoder=se3_kattention", "model.body_frame_obs=false", "model.encoder_kwargs.out_vectors=30"],
     r"model.encoder_kwargs.*out_vectors=30"),
])
def test_validate_checks_names_symmetry_and_encoder_options(overrides, message):
    with pytest.raises(ConfigError, match=message):
        load_config(None, overrides)


@pytest.mark.parametrize("encoder", ["se3_graphormer", "se3_kattention", "graphormer", "kattention", "mlp"])
def test_any_encoder_on_the_quickstart_uses_its_own_small_sizes(encoder):
    import encoders
    from swarm_appo.model import model_factory

    cfg = load_config(None, [f"model.encoder={encoder}"])  # body_frame_obs auto: the symmetry does it, if any
    assert cfg.model.size == "small" and cfg.model.encoder_kwargs == {} and cfg.model.body_frame_obs is None
    model = model_factory(cfg.env.obs_layout(), cfg.model)()
    assert (model.body_frame is not None) == (encoders.resolve(encoder)[1] == "none")
    assert model.actor_encoder.out_dim == 64 and model.actor_head[0].out_features == 64
    cfg = load_config("configs/paper.yaml", [f"model.encoder={encoder}", "model.size=small"])
    assert cfg.model.size == "small"


def test_validate_type_checks_trees_built_in_code():
    cfg = TrainConfig(algo=AlgoConfig(lr="fast"))
    with pytest.raises(ConfigError, match="'algo.lr' expects float"):
        validate(cfg)


def test_dict_round_trip_and_strictness():
    cfg = load_config(PAPER_YAML, ["model.encoder_kwargs={multiplicity: 16}", "wandb.tags=[x]"])
    d = config_to_dict(cfg)
    assert d["algo"]["adam_betas"] == [0.9, 0.995] and d["env"]["reward"]["pos"] == 0.5
    assert config_from_dict(d) == cfg
    assert config_from_dict({}) == TrainConfig()
    d["runner"]["bogus"] = 1
    with pytest.raises(ConfigError, match="'runner.bogus'"):
        config_from_dict(d)
    with pytest.raises(ConfigError, match="mapping"):
        config_from_dict([1, 2])


def test_save_config_round_trips_through_yaml(tmp_path):
    cfg = load_config(PAPER_YAML, ["env.sensing_radius=1.5", "algo.value_clip=0.2", "wandb.tags=[a]",
                                   "model.encoder_kwargs={multiplicity: 8}"])
    path = tmp_path / "run" / "config.yaml"
    save_config(cfg, path)
    assert sorted(p.name for p in path.parent.iterdir()) == ["config.yaml"]  # no temp file left
    assert load_config(str(path)) == cfg
    assert config_from_dict(yaml.safe_load(path.read_text())) == cfg  # plain YAML readers work too
    save_config(load_config(None), path)  # replaced atomically
    assert load_config(str(path)) == load_config(None)


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(str(tmp_path / "missing.yaml"))
    bad = tmp_path / "bad.yaml"
    bad.write_text("algo:\n  learning_rate: 0.1\n")
    with pytest.raises(ConfigError, match=r"bad.yaml.*'algo.learning_rate'"):
        load_config(str(bad))
    bad.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="bad.yaml.*mapping"):
        load_config(str(bad))
    bad.write_text("algo: {lr: [\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(str(bad))
    empty = tmp_path / "empty.yaml"
    empty.write_text("")
    assert load_config(str(empty)) == TrainConfig()


def test_config_error_is_a_value_error():
    assert issubclass(ConfigError, ValueError)


@pytest.mark.parametrize("row,encoder,symmetry", [("se3_graphormer", "graphormer", "se3"),
                                                  ("se3_kattention", "kattention", "se3"),
                                                  ("kattention", "kattention", "none"),
                                                  ("deepsets", "deepsets", "none"),
                                                  ("infomarl", "infomarl", "none")])
def test_paper_row_configs_are_the_paper_config_with_two_keys(row, encoder, symmetry):
    from swarm_appo.config import config_to_dict
    paper = config_to_dict(load_config("configs/paper.yaml"))
    cfg = load_config(f"configs/paper/{row}.yaml")
    assert cfg.env.scenario == "mix" and cfg.model.size == "paper"  # Table 1: trained on all scenarios
    assert (cfg.model.encoder, cfg.model.symmetry) == (encoder, symmetry)
    d = config_to_dict(cfg)
    for section in ("env", "algo"):
        assert d[section] == paper[section]
    assert {k for k in d["model"] if d["model"][k] != paper["model"][k]} <= {"encoder", "symmetry"}


def test_rmappo_row_is_the_paper_config_with_rmappos_network():
    from swarm_appo.config import config_to_dict
    paper = config_to_dict(load_config("configs/paper.yaml"))
    cfg = load_config("configs/paper/rmappo.yaml")
    m = cfg.model
    assert (m.encoder, m.symmetry, m.size, m.core, m.critic) == ("mlp", "none", "small", "gru", "central")
    d = config_to_dict(cfg)
    assert d["env"] == paper["env"] and d["algo"] == paper["algo"]
    assert {k for k in d["model"] if d["model"][k] != paper["model"][k]} == {"encoder", "symmetry", "size", "core",
                                                                              "critic"}


def _trained_keys_that_differ(base: dict, other: dict) -> set:
    """"section.key" of every env/model/algo setting (what shapes training) where two config dicts differ."""
    return {f"{section}.{k}" for section in ("env", "model", "algo") for k in other[section]
            if other[section][k] != base[section][k]}


def test_quality_config_is_the_table1_recipe_with_what_moved_the_quality_goal():
    from swarm_appo.config import config_to_dict
    recipe = config_to_dict(load_config("configs/table1/recipe.yaml"))
    quality = config_to_dict(load_config("configs/table1/quality.yaml"))
    assert _trained_keys_that_differ(recipe, quality) == {
        "env.replay_prob", "model.symmetry", "algo.lr", "algo.batch_size", "algo.num_epochs", "algo.lr_schedule",
        "algo.ppo_clip_ratio", "algo.weight_ema"}  # the last a read-out, not a training change
    assert (quality["algo"]["lr"], quality["algo"]["batch_size"], quality["algo"]["num_epochs"]) == (1e-4, 4096, 5)
    paper = config_to_dict(load_config(PAPER_YAML))
    assert quality["algo"]["ppo_clip_ratio"] == paper["algo"]["ppo_clip_ratio"] == 0.1  # Sample Factory's default


def test_base_config_errors_name_the_file(tmp_path):
    (tmp_path / "a.yaml").write_text("base: b.yaml\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    with pytest.raises(ConfigError, match="cycle"):
        load_config(str(tmp_path / "a.yaml"))
    (tmp_path / "c.yaml").write_text("base: missing.yaml\nalgo: {lr: 1.0e-3}\n")
    with pytest.raises(ConfigError, match="missing.yaml"):
        load_config(str(tmp_path / "c.yaml"))
    (tmp_path / "d.yaml").write_text("base: ../configs/paper.yaml\nalgo: {lrr: 1}\n")
    with pytest.raises(ConfigError, match="d.yaml.*algo.lrr"):
        load_config(str(tmp_path / "d.yaml"))


# ----------------------------------------------------------------------------------------------- fuzz: non-finite
def _float_keys(cls, prefix=""):
    """(dotted key, tuple length or None) of every float field in the config tree, tuples of floats included."""
    import dataclasses
    import typing

    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        tp, key = hints[f.name], f"{prefix}{f.name}"
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if typing.get_origin(tp) is typing.Union and len(args) == 1:
            tp = args[0]  # Optional[X] -> X
        if dataclasses.is_dataclass(tp):
            yield from _float_keys(tp, f"{key}.")
        elif tp is float:
            yield key, None
        elif typing.get_origin(tp) is tuple and typing.get_args(tp) and typing.get_args(tp)[0] is float:
            default = getattr(cls(), f.name)
            yield key, len(default) if default is not None else 3


FLOAT_KEYS = sorted(_float_keys(TrainConfig))


def test_the_config_tree_has_many_float_fields():
    assert len(FLOAT_KEYS) >= 60  # the fuzz below covers every one of them
    assert ("algo.lr", None) in FLOAT_KEYS and ("env.reward.pos", None) in FLOAT_KEYS


@pytest.mark.parametrize("bad", [".inf", "-.inf", ".nan"])
def test_every_non_finite_float_is_a_config_error_naming_its_key(bad):
    """A few hundred generated bad overrides (every float field x inf, -inf, nan): each a ConfigError naming
    the key, none a traceback from deeper down."""
    failures = []
    for key, length in FLOAT_KEYS:
        value = bad if length is None else "[" + ", ".join([bad] + ["0.5"] * (length - 1)) + "]"
        try:
            validate(load_config(None, [f"{key}={value}"]))
            failures.append(f"{key}={value}: accepted")
        except ConfigError as exc:
            if key not in str(exc):
                failures.append(f"{key}={value}: message does not name the key: {exc}")
        except Exception as exc:  # noqa: BLE001 - the point is that nothing else escapes
            failures.append(f"{key}={value}: {type(exc).__name__}: {exc}")
    assert not failures, "\n".join(failures)


@pytest.mark.parametrize("override, fragment", [
    ("model.init_log_std=1e6", "model.init_log_std"), ("model.init_log_std=-50", "model.init_log_std"),
    ("runner.seed=1e30", "runner.seed"),
])
def test_finite_but_absurd_values_are_errors(override, fragment):
    with pytest.raises(ConfigError, match=fragment.replace(".", r"\.")):
        validate(load_config(None, [override]))


def test_a_cuda_device_that_is_not_there_fails_before_the_run_dir(tmp_path, monkeypatch):
    import torch

    from swarm_appo.trainer import train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 0)
    cfg = load_config(None, ["runner.device=cuda:0", f"runner.run_dir={tmp_path}", "runner.serial=true",
                             "wandb.mode=disabled"])
    with pytest.raises(ConfigError, match=r"runner\.device=cuda:0"):
        train(cfg, progress=False)
    assert not any(tmp_path.iterdir())


def test_hour_config_is_the_quality_recipe_in_serial_mode_for_40_m_steps():
    from swarm_appo.config import config_to_dict
    quality = config_to_dict(load_config("configs/table1/quality.yaml"))
    hour = config_to_dict(load_config("configs/table1/hour.yaml"))
    assert _trained_keys_that_differ(quality, hour) == set()
    assert hour["algo"]["ppo_clip_ratio"] == 0.1  # the clip of the three measured hours
    assert hour["runner"]["serial"] is True and hour["runner"]["total_agent_steps"] == 40_000_000
    assert hour["algo"]["lr_schedule"] == "linear"  # the decay reaches 0 at the 40-M budget
