"""Shared fixtures for the swarm_appo tests (``one_torch_thread`` lives in tests/conftest.py)."""
