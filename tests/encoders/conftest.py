import pytest


@pytest.fixture(autouse=True)
def _tiny_models_on_one_thread(one_torch_thread):
    """Tests of tiny models run fastest (and least disturbed by parallel jobs) on one thread."""
    yield
