"""Playing the envs: the on-policy rollout collector, the replay collector of the off-policy
algorithms (in this process or in the env workers), exploration, and evaluation episodes."""
