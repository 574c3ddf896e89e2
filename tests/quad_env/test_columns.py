"""The reward-term rows and the accumulator columns derive from one ordered list each: distinct, contiguous."""
from quad_env import kernels, params
from quad_env.config import REWARD_TERMS, RewardConfig


def _int_constants(module, prefix):
    return {name: v for name, v in vars(module).items() if name.startswith(prefix) and isinstance(v, int)}


def test_term_rows_follow_reward_terms():
    rows = _int_constants(params, "T_")
    assert rows == {"T_" + name.upper(): k for k, name in enumerate(REWARD_TERMS)}
    assert REWARD_TERMS[-1] == "crash" and params.KERNEL_TERMS == len(REWARD_TERMS) - 1  # VecQuadEnv adds the last
    assert all(isinstance(getattr(RewardConfig(), name), float) for name in REWARD_TERMS)  # each has a coefficient


def _assert_covers(columns, singles, blocks, total):
    """Every column is named once: the single columns plus the blocks (start, width) tile range(total)."""
    covered = sorted(list(singles.values()) + [c for start, width in blocks for c in range(start, start + width)])
    assert covered == list(range(total)) and len(columns) == total and len(set(columns)) == total


def test_accumulator_columns_are_distinct_contiguous_and_terms_in_order():
    singles = _int_constants(kernels, "ACC_")
    start = singles.pop("ACC_TERMS")
    _assert_covers(kernels.ACC_COLUMNS, singles, [(start, len(REWARD_TERMS))], kernels.NUM_ACC)
    assert kernels.ACC_COLUMNS[start:start + len(REWARD_TERMS)] == tuple("term_" + t for t in REWARD_TERMS)
    for name, column in singles.items():
        assert kernels.ACC_COLUMNS[column] == name[len("ACC_"):].lower()


def test_agent_accumulator_columns_are_distinct_and_contiguous():
    singles = _int_constants(kernels, "AG_")
    ring = singles.pop("AG_RING")
    _assert_covers(kernels.AG_COLUMNS, singles, [(ring, kernels.SUCCESS_WINDOW)], kernels.NUM_AGENT_ACC)
    for name, column in singles.items():
        assert kernels.AG_COLUMNS[column] == name[len("AG_"):].lower()
