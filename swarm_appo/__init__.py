"""swarm_appo package."""
